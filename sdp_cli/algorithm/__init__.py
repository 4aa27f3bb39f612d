"""The paper's Algorithm 1 and 2: collect TO trajectories (:mod:`.collect`, :mod:`.solve_jobs`), roll a policy out
(:mod:`.rollout`), refine its rollouts by TO (:mod:`.refine`, :mod:`.argmin`), evaluate (:mod:`.evaluate`) and the
loop that ties them (:mod:`.loop`, its options in :mod:`.loop_options`). Above training and execution, below the
experiments."""

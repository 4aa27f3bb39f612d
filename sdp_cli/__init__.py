"""sdp: Sobolev Diffusion Policy toolkit (trajectory optimization + diffusion policies)."""

__version__ = "0.1.0"

#: Version of what runs measure. A commit that changes the numbers a run produces (chunk sampling, a
#: task's definition, a loss, a solver's stopping rule, ...) bumps it; a comment, a refactor or a
#: report change does not. Every loop run records it (``loop_config.json``), and the DVC stage starts
#: over (after moving the old folder aside, never deleting it) only runs of another results version
#: or other settings. History: 1 = everything before 2026-11-27; 2 = chunks cover the episode end,
#: UR5 and quadrotor redefined (issue "A perfect learner must score TO's cost"); 3 = UR5 random
#: targets kept 0.1 m inside the arm's reach (at most 0.85 m from the shoulder), same issue; 4 = the
#: trainer's fused AdamW and foreach EMA, and one-iteration runs trained in stacks (issue "Many runs at
#: once": the same arithmetic, rounded otherwise, so a seed's training takes another path).
RESULTS_VERSION = 4

"""sdp: Sobolev Diffusion Policy toolkit (trajectory optimization + diffusion policies)."""

__version__ = "0.1.0"

from sdp_cli.kernels import cap_cpu_kernels as _cap_cpu_kernels, use_compile_cache as _use_compile_cache
from sdp_cli.moved import install as _install_moved

#: torch's and numpy's CPU kernels capped at the AVX2 level before either runs one, unless the user chose
#: (sdp_cli/kernels.py): the same seed then gives the same numbers on x86 CPUs with and without AVX-512
_cap_cpu_kernels()
_use_compile_cache()   # inductor's cache folder, before anything imports torch._dynamo (sdp_cli/kernels.py)
_install_moved()   # the modules' import paths before the layer folders (sdp_cli/moved.py)

#: the heavy dependencies, imported inside the functions that use them (and so are the modules of sdp that import
#: them at module level), so that `sdp --help` and the light commands start without them; every other import is
#: at module level, except the few that must run late (the CLI entry's, optional ones, a package's lazy
#: attributes): tests/test_imports.py checks both
LAZY_IMPORTS = ("torch", "diffusers", "pandas", "matplotlib", "scipy", "dask", "distributed", "yaml", "rich")

#: Version of what runs measure. A commit that changes the numbers a run produces (chunk sampling, a
#: task's definition, a loss, a solver's stopping rule, ...) bumps it and says what changed in
#: :data:`RESULTS_HISTORY`; a comment, a refactor or a report change does not. Every loop run records it
#: (``loop_config.json``; runs before version 4 did not: the report reads it from their code revision,
#: sdp_cli/report/versions.py), and the DVC stage starts over (after moving the old folder aside, never
#: deleting it) only runs of another results version or other settings. The literal below is what the report
#: parses at an old revision: keep it an integer literal.
RESULTS_VERSION = 7

#: What each results version changed (the ledger, results/PAPER.md, prints the entries newer than its oldest run).
RESULTS_HISTORY = {
    1: "everything before 2026-11-27",
    2: ("chunks cover the episode end (before, a perfect learner, the nearest-neighbour memorizer of the training "
        "chunks, scored 1479x and 2921x TO's cost on its own UR5 training instances at (T_h 64, T_a 63)); UR5 "
        "redefined (one step late cost 33-106x its optimum: a stop-timing test) and the quadrotor too (its optimum "
        "ended 55-72% of the success tolerance from the goal, still moving), so that a policy without a time input "
        "can match the optimum (issue \"A perfect learner must score TO's cost\"; results/tasks/timing.md, "
        "results/tasks/confirmation.md)"),
    3: "UR5 random targets kept 0.1 m inside the arm's reach (at most 0.85 m from the shoulder)",
    4: ("the trainer's fused AdamW and foreach EMA, and one-iteration runs trained in stacks (issue \"Many runs at "
        "once\": the same arithmetic rounded otherwise, so a seed's training takes another path)"),
    5: ("the quadrotor's state-action policies turn their predicted chunks into thrusts by the tracking conversion "
        "(a time-varying LQR around the chunk; before: one-step inverse dynamics of each row), its default by the "
        "conversion rule (results/tasks/conversion_rule.md): collection warm starts and evaluations of quadrotor "
        "loops change; other tasks' runs measure what they did (evaluation rows carry a conversion column)"),
    6: ("box-FDDP (`--to ddp`) iterates with PSD-projected cost Hessians and polishes a converged solution before "
        "taking its gains: from the naive guess the double pendulum lands on other local optima (every one of 32 "
        "instances; UR5, quadrotor-0 and the pendulum keep theirs; docs/trajopt.md), so `-ddp` runs and box-FDDP's "
        "TO-alone rows change; `sdp pipeline --run` trains loops of several iterations as stacks in lockstep "
        "(their weights differ from solo training at float32 rounding); fatrop runs of one iteration measure what "
        "they did"),
    7: ("the diffusion policies of fig1-fig4 and ablation_k train compiled (torch.compile of the U-Net's forward "
        "and tangent pass: the loss differs from eager by ~1e-7, gradients by ~1.5e-6 relative; `small` stays "
        "eager and unchanged); stacks keyed by network shape: runs of one method, architecture, batch and network "
        "sizes share a stack whatever their task variant, seed or T_a (before: one task a stack), so such runs "
        "round otherwise"),
}

#: Which rows each version's change touches, where it is not every row: a list of alternatives, each a mapping of
#: conditions that all hold (``methods``: the method a row is of; ``task_prefix``; ``to``: the TO family;
#: ``min_n_algo``: loops of at least that many iterations). A row of an older version is read beside a newer
#: version's rows of its task only where no version since its own touches it (:func:`sdp_cli.report.rows.newest_version`):
#: the MLPs act on torques and train eager, so versions 5 and 7 leave their runs measuring what they did.
RESULTS_SCOPE = {
    5: [{"task_prefix": "quadrotor", "methods": ["sdp", "dp"]}],
    6: [{"to": ["ddp"]}, {"min_n_algo": 2}],
    7: [{"methods": ["sdp", "dp"]}],
}

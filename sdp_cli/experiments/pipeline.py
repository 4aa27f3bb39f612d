"""Experiment definitions (``pipelines/<name>.yaml``): the runs of an experiment, and what DVC runs.

An experiment file lists *groups*; each group is a sweep::

    description: ...
    groups:
      - task: pendulum
        methods: [sdp, dp]
        seeds: [0, 1]
        n_traj: [3, 10]        # one run per value (Fig. 1's sweep); a loop uses one value
        # n_traj_schedule: [30, 50, 70]   # instead: one run, trajectories per iteration (the last repeats)
        n_algo: 1              # iterations of Algorithm 1
        epochs: 1000           # n_pl per iteration
        save_at: [500]         # extra epoch counts evaluated (Fig. 1)
        horizon: 16            # T_h
        t_a: 8                 # T_a of the warm-starting rollouts
        eval_t_a: [8]          # T_a values evaluated on the test set at every iteration
        eval_t_a_last: [1, 4]  # extra T_a values evaluated at the last iteration only (Table 2c)
        n_test: 50             # every rollout/evaluation option of `sdp loop` is a key (sdp_cli.algorithm.loop_options):
        eval_refine: true      #   t_a, eval_t_a, eval_t_a_last, k_rollout, conversion, n_test, test_seed,
                               #   single_shooting, eval_refine
        train: {batch_size: 256, sobolev_alpha: 1.0}   # optional: any other training option (`sdp train --help`)
        tag: h16               # optional: appended to the run names (groups that differ only in settings)

Every (group, method, seed, n_traj) is one *run*: one ``sdp loop``, Algorithm 1 as
:func:`sdp_cli.algorithm.loop.run_loop` implements it (the one implementation, used by ``sdp loop``,
``sdp pipeline NAME --run`` and DVC alike), in ``runs/<name>/<task>-<method>-n<n_traj>-s<seed>[-<tag>]/``
(:func:`loop_configs`). ``sdp pipeline NAME`` writes ``experiment: NAME`` and one ``group``
entry into ``params.yaml``; ``dvc repro`` then runs the DVC stage ``group``, which runs every run
of the experiment in parallel through the executor of ``SDP_EXECUTOR``/``SDP_WORKERS``/
``SDP_SCHEDULER`` (:mod:`sdp_cli.experiments.runner`), with a persistent output so that an interrupted
``dvc repro`` resumes the runs instead of deleting them, and then the ``report`` stage.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import yaml

from sdp_cli.errors import SdpError
from sdp_cli.experiments.experiment import check_group, group_items, group_where, load_experiment, run_name, type_ok
from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, from_group
from sdp_cli.data.artifacts import atomic_write_bytes, check_writable
from sdp_cli.policy.config import RENAMED, TrainConfig, option_type, options
from sdp_cli.seeds import check_loop_seed

#: training options a group sets with its own keys (a sweep: ``methods``, ``seeds``; or the group-level
#: ``epochs``, ``horizon``, ``save_at``, of the same names); ``train:`` may set every other one
_GROUP_OWNED = {"method", "epochs", "seed", "horizon", "save_at"}


def train_option_names() -> set[str]:
    """The keys a group's ``train:`` may set: the training options (:func:`sdp_cli.policy.config.options`)
    not owned by the group."""
    return set(options()) - _GROUP_OWNED


def train_option_type(name: str) -> str:
    """The :func:`sdp_cli.experiments.experiment.type_ok` spec of a training option, from its field's annotation."""
    base, item, optional = option_type(name)
    return (f"[{item.__name__}]" if item is not None else base.__name__) + ("?" if optional else "")


def loop_configs(name: str, spec: dict) -> dict[str, "LoopConfig"]:  # noqa: F821 (sdp_cli.algorithm.loop.LoopConfig)
    """``{run name: LoopConfig}`` of every run of an experiment, each validated (task, method,
    options, T_a) before anything runs; an error names the file, the group and the key."""
    from sdp_cli.experiments.experiment import describe_type

    runs = {}
    for gi, raw in group_items(spec):
        g = check_group(name, gi, raw)
        where = group_where(name, gi)
        bad = set(g["train"] or {}) - train_option_names()
        if bad:
            hint = "".join(f" ({k} is now {RENAMED[k]})" for k in sorted(bad) if k in RENAMED)
            raise SdpError(f"{where}: unknown train option(s) {sorted(bad)}{hint}; known: "
                           f"{', '.join(sorted(train_option_names()))}")
        for key, value in (g["train"] or {}).items():
            if not type_ok(value, train_option_type(key)):
                raise SdpError(f"{where}, key 'train.{key}': must be {describe_type(train_option_type(key))}, "
                               f"got {value!r}")
        for method, seed, n_traj in itertools.product(g["methods"], g["seeds"], g["n_traj"]):
            key = run_name(g["task"], method, n_traj, seed, g["tag"])
            if key in runs:
                raise SdpError(f"experiment {name!r}: run {key} appears in two groups (give them different `tag`s)")
            try:
                runs[key] = _loop_config(g, method, seed, n_traj)
            except SdpError as e:
                raise SdpError(f"{where}: {e}") from None
    return runs


def check_only(name: str, runs: dict, only: list[str] | None) -> None:
    """``--only``'s run names must be runs of experiment ``name`` (``runs``: its :func:`loop_configs`)."""
    unknown = sorted(set(only or ()) - set(runs))
    if unknown:
        raise SdpError(f"experiment {name!r} has no run {', '.join(unknown)}; runs: {', '.join(runs)}")


def _loop_config(g: dict, method: str, seed: int, n_traj: int) -> "LoopConfig":  # noqa: F821
    from sdp_cli.algorithm.loop import LoopConfig

    check_loop_seed(seed, "seed", g["n_algo"])   # the loop's rule (collection seeds) before the trainer's

    train = TrainConfig.of(**{**(g["train"] or {}), "method": method, "epochs": g["epochs"], "seed": seed,
                              "horizon": g["horizon"], "save_at": [int(e) for e in g["save_at"] if e < g["epochs"]]})
    rollout = from_group(g)   # every loop option is a group key (sdp_cli.algorithm.loop_options)
    return LoopConfig(task=g["task"], train=train, rollout=rollout, **from_group(g, LoopAlgorithmOptions),
                      n_traj=tuple(int(n) for n in (g["n_traj_schedule"] or [n_traj])), workers=1, device="cpu")


def select_experiment(name: str, params_path: Path = Path("params.yaml"), root: Path = Path(".")) -> dict:
    """Validate experiment ``name`` (every run, not hours into ``dvc repro``) and select it in ``params.yaml``;
    returns ``{"runs": n}``. The experiment's settings are DVC parameters of ``pipelines/NAME.yaml`` itself
    (``dvc.yaml``'s stage ``group``): ``dvc exp run -S 'pipelines/NAME.yaml:groups.GROUP.epochs=100'``,
    ``dvc params diff``, ``dvc exp show``."""
    spec = load_experiment(name, root)
    n = len(loop_configs(name, spec))
    check_writable(params_path)   # a regular file or none (a fifo would block the read below)
    params = {}
    if params_path.exists():
        params = yaml.safe_load(params_path.read_text()) or {}
    params.pop("experiment_stages", None)     # written by sdp before results version 2
    params["experiment"] = name
    header = ("# The experiment `dvc repro` runs: pipelines/<experiment>.yaml, whose settings are DVC parameters\n"
              "# (dvc exp run -S 'pipelines/small.yaml:groups.pendulum-sdp-dp.epochs=100'). Written by\n"
              "# `sdp pipeline NAME`.\n")

    atomic_write_bytes(params_path, lambda f: f.write((header + yaml.safe_dump(params, sort_keys=False)).encode()))
    return {"runs": n}

"""Experiment files (``pipelines/<name>.yaml``): reading them and naming their runs.

The format and what runs them are described in :mod:`sdp_cli.pipeline`; this module is what
``sdp report`` needs (no training, optimizer or policy code), so a report does not depend on them.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import yaml

from sdp_cli.errors import SdpError

PIPELINES_DIR = Path("pipelines")
GROUP_DEFAULTS = {"methods": ["sdp"], "seeds": [0], "n_traj": [30], "n_algo": 1, "epochs": 1000, "save_at": [],
                  "horizon": 32, "t_a": None, "eval_t_a": [], "eval_t_a_last": [], "k_rollout": None, "n_test": 50,
                  "test_seed": 0, "max_iter": 1000, "single_shooting": False, "train": {}, "tag": None,
                  "n_traj_schedule": None}


def load_experiment(name: str, root: Path = Path(".")) -> dict:
    path = root / PIPELINES_DIR / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (root / PIPELINES_DIR).glob("*.yaml"))
        raise SdpError(f"unknown experiment {name!r}; known: {', '.join(known) or 'none'} (in {PIPELINES_DIR}/)")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SdpError(f"invalid experiment file {path}: {e}") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("groups"), list):
        raise SdpError(f"invalid experiment file {path}: needs a 'groups' list")
    unknown = set(spec) - {"description", "groups"}
    if unknown:
        raise SdpError(f"invalid experiment file {path}: unknown keys {sorted(unknown)}")
    return spec


def check_group(name: str, gi: int, raw: dict) -> dict:
    """Group ``gi`` of experiment ``name`` with the defaults filled in (``SdpError`` on unknown keys;
    the ``train:`` options are checked by :func:`sdp_cli.pipeline.loop_configs`)."""
    if not isinstance(raw, dict):
        raise SdpError(f"experiment {name!r}, group {gi}: expected a mapping, got {raw!r}")
    unknown = set(raw) - set(GROUP_DEFAULTS) - {"task"}
    if unknown:
        raise SdpError(f"experiment {name!r}, group {gi}: unknown keys {sorted(unknown)}")
    if "task" not in raw:
        raise SdpError(f"experiment {name!r}, group {gi}: 'task' is required")
    g = {**GROUP_DEFAULTS, **raw}
    sched = g["n_traj_schedule"]
    if sched is not None:
        if not (isinstance(sched, list) and sched and all(isinstance(n, int) and n > 0 for n in sched)):
            raise SdpError(f"experiment {name!r}, group {gi}: n_traj_schedule must be a list of positive integers "
                           f"(trajectories per iteration), got {sched!r}")
        if "n_traj" in raw:
            raise SdpError(f"experiment {name!r}, group {gi}: give n_traj (a sweep) or n_traj_schedule (per "
                           "iteration), not both")
        g["n_traj"] = [sched[0]]   # the run's name carries the first iteration's count
    return g


def run_name(task: str, method: str, n_traj: int, seed: int, tag: str | None = None) -> str:
    """The folder of one run."""
    return f"{task}-{method}-n{n_traj}-s{seed}" + (f"-{tag}" if tag else "")


def group_run_names(g: dict) -> list[str]:
    """The run names of one checked group (:func:`check_group`): methods x seeds x n_traj."""
    return [run_name(g["task"], m, n, s, g["tag"]) for m, s, n in itertools.product(g["methods"], g["seeds"], g["n_traj"])]


def run_names(name: str, spec: dict) -> list[str]:
    """The run names of an experiment (cheap: no run is validated)."""
    return [k for gi, raw in enumerate(spec["groups"]) for k in group_run_names(check_group(name, gi, raw))]

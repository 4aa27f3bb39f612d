"""Experiment files (``pipelines/<name>.yaml``): reading them and naming their runs.

The format and what runs them are described in :mod:`sdp_cli.experiments.pipeline`; this module is what
``sdp report`` needs (no training, optimizer or policy code), so a report does not depend on them.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import yaml

from sdp_cli.errors import SdpError
from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, LoopRolloutConfig, group_keys

PIPELINES_DIR = Path("pipelines")
#: the group keys that are not loop options (those come from the fields of sdp_cli.algorithm.loop_options: below): what a
#: group sweeps (methods x seeds x n_traj) and names, and the training options of its runs
_GROUP_OWN = {"task": ("str", None), "methods": ("[str]", ["sdp"]), "seeds": ("[int]", [0]),
              "n_traj": ("[int]", [30]), "epochs": ("int", 1000), "save_at": ("[int]", []),
              "horizon": ("int", 32), "train": ("dict", {}), "tag": ("str?", None),
              "n_traj_schedule": ("[int]?", None)}
_GROUP_KEYS = {**_GROUP_OWN, **group_keys(LoopAlgorithmOptions), **group_keys(LoopRolloutConfig)}
GROUP_DEFAULTS = {k: d for k, (_, d) in _GROUP_KEYS.items() if k != "task"}


def load_experiment(name: str, root: Path = Path(".")) -> dict:
    path = root / PIPELINES_DIR / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in (root / PIPELINES_DIR).glob("*.yaml"))
        raise SdpError(f"unknown experiment {name!r}; known: {', '.join(known) or 'none'} (in {PIPELINES_DIR}/)")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SdpError(f"invalid experiment file {path}: {e}") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("groups"), (dict, list)) or not spec["groups"]:
        raise SdpError(f"invalid experiment file {path}: needs 'groups', a mapping of group names to groups")
    unknown = set(spec) - {"description", "groups"}
    if unknown:
        raise SdpError(f"invalid experiment file {path}: unknown keys {sorted(unknown)}")
    return spec


#: the type of each group key: "int", "int?" (or null), "[int]" (a list of), "str", "bool", "dict"
GROUP_TYPES = {k: spec for k, (spec, _) in _GROUP_KEYS.items()}
#: the keys whose values multiply into the group's runs (methods x seeds x n_traj)
SWEEP_KEYS = ("methods", "seeds", "n_traj")
_PY = {"int": int, "str": str, "bool": bool, "dict": dict, "float": (int, float)}


def type_ok(value, spec: str) -> bool:
    """``value`` has the type ``spec`` of :data:`GROUP_TYPES` (a bool is not an int)."""
    if spec.endswith("?"):
        return value is None or type_ok(value, spec[:-1])
    if spec.startswith("["):
        return isinstance(value, list) and all(type_ok(v, spec[1:-1]) for v in value)
    if spec in ("int", "float") and isinstance(value, bool):
        return False
    return isinstance(value, _PY[spec])


def describe_type(spec: str) -> str:
    words = {"int": "an integer", "str": "a string", "bool": "true or false", "dict": "a mapping",
             "float": "a number"}
    if spec.endswith("?"):
        return describe_type(spec[:-1]) + " (or null)"
    if spec.startswith("["):
        return "a list of " + {"int": "integers", "str": "strings", "float": "numbers"}[spec[1:-1]] + ", e.g. [1, 2]"
    return words[spec]


def group_where(name: str, gi: int) -> str:
    """How an error names a group: the file and the group's index."""
    return f"{PIPELINES_DIR / (name + '.yaml')}, group {gi}"   # a name, or a list index


def check_group(name: str, gi: int, raw: dict) -> dict:
    """Group ``gi`` of experiment ``name`` with the defaults filled in (``SdpError`` on unknown keys;
    the ``train:`` options are checked by :func:`sdp_cli.experiments.pipeline.loop_configs`)."""
    where = group_where(name, gi)
    if not isinstance(raw, dict):
        raise SdpError(f"{where}: expected a mapping, got {raw!r}")
    unknown = set(raw) - set(GROUP_DEFAULTS) - {"task"}
    if unknown:
        raise SdpError(f"{where}: unknown keys {sorted(unknown)}")
    if "task" not in raw:
        raise SdpError(f"{where}: 'task' is required")
    for key, value in raw.items():
        if not type_ok(value, GROUP_TYPES[key]):
            raise SdpError(f"{where}, key {key!r}: must be {describe_type(GROUP_TYPES[key])}, got {value!r}")
    for key in SWEEP_KEYS:   # an empty sweep is a group of no runs: a typo, not a choice
        if key in raw and not raw[key]:
            raise SdpError(f"{where}, key {key!r}: must list at least one value (a group of no runs), got []")
    g = {**GROUP_DEFAULTS, **raw}
    sched = g["n_traj_schedule"]
    if sched is not None:
        if not (isinstance(sched, list) and sched and all(isinstance(n, int) and n > 0 for n in sched)):
            raise SdpError(f"{where}, key 'n_traj_schedule': must be a list of positive integers "
                           f"(trajectories per iteration), got {sched!r}")
        if "n_traj" in raw:
            raise SdpError(f"{where}: give n_traj (a sweep) or n_traj_schedule (per "
                           "iteration), not both")
        g["n_traj"] = [sched[0]]   # the run's name carries the first iteration's count
    return g


def group_items(spec: dict) -> list[tuple[str, dict]]:
    """``(name, group)`` of every group: ``groups`` is a mapping keyed by group name (what DVC's
    ``dvc exp run -S 'pipelines/NAME.yaml:groups.GROUP.epochs=...'`` can address), or a list (named by index)."""
    groups = spec["groups"]
    return [(str(k), g) for k, g in (groups.items() if isinstance(groups, dict) else enumerate(groups))]


def run_name(task: str, method: str, n_traj: int, seed: int, tag: str | None = None) -> str:
    """The folder of one run."""
    return f"{task}-{method}-n{n_traj}-s{seed}" + (f"-{tag}" if tag else "")


def group_run_names(g: dict) -> list[str]:
    """The run names of one checked group (:func:`check_group`): methods x seeds x n_traj."""
    return [run_name(g["task"], m, n, s, g["tag"]) for m, s, n in itertools.product(g["methods"], g["seeds"], g["n_traj"])]


def run_names(name: str, spec: dict) -> list[str]:
    """The run names of an experiment (cheap: no run is validated)."""
    return [k for gi, raw in group_items(spec) for k in group_run_names(check_group(name, gi, raw))]

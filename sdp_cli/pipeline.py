"""Experiment definitions (``pipelines/<name>.yaml``) expanded into DVC stage lists.

An experiment file lists *groups*; each group is a sweep::

    description: ...
    groups:
      - task: pendulum
        methods: [sdp, dp]
        seeds: [0, 1]
        n_traj: [3, 10]        # one run per value (Fig. 1's sweep); a loop uses one value
        n_algo: 1              # iterations of Algorithm 1
        epochs: 1000           # n_pl per iteration
        save_at: [500]         # extra epoch counts evaluated (Fig. 1)
        horizon: 16            # T_h
        t_a: 8                 # T_a of the warm-starting rollouts
        eval_t_a: [8]          # T_a values evaluated on the test set at every iteration
        eval_t_a_last: [1, 4]  # extra T_a values evaluated at the last iteration only (Table 2c)
        n_test: 50
        train: {batch_size: 256, alpha_sobolev: 1.0}   # optional extra `sdp train` options

:func:`expand` turns it into three dictionaries that ``dvc.yaml`` iterates with
``foreach``: ``collect_first`` (iteration 0, naive guess), ``collect_next`` and
``train_next`` (iterations k > 0, each naming its predecessor's policy), ``train_first`` and
``evaluate`` (one entry per checkpoint x T_a). ``sdp pipeline NAME`` writes them into
``params.yaml`` under ``experiment_stages`` and sets ``experiment: NAME``; ``dvc repro`` then
runs exactly that experiment.

``runner: group`` at the top of an experiment file selects the other way to run it: one DVC
stage ``group`` that runs every run (an ``sdp loop``) in parallel through the executor of
``SDP_EXECUTOR``/``SDP_WORKERS``/``SDP_SCHEDULER`` (:mod:`sdp_cli.runner`), with a persistent
output so that an interrupted ``dvc repro`` resumes the runs instead of deleting them.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import yaml

from sdp_cli.errors import SdpError

PIPELINES_DIR = Path("pipelines")
#: how `dvc repro` runs an experiment: one DVC stage per step (``stages``, the default) or one
#: stage running every run through the executor (``group``, parallel; :mod:`sdp_cli.runner`)
RUNNERS = ("stages", "group")
GROUP_DEFAULTS = {"methods": ["sdp"], "seeds": [0], "n_traj": [30], "n_algo": 1, "epochs": 1000, "save_at": [],
                  "horizon": 32, "t_a": None, "eval_t_a": [], "eval_t_a_last": [], "k_rollout": None, "n_test": 50, "test_seed": 0,
                  "max_iter": 1000, "single_shooting": False, "train": {}}
_TRAIN_FLAGS = {"batch_size": "--batch-size", "alpha_sobolev": "--alpha-sobolev", "lr": "--lr",
                "n_proj": "--n-proj", "sobolev_mode": "--sobolev-mode", "diffusion_steps": "--diffusion-steps",
                "action": "--action", "sobolev_cap": "--sobolev-cap", "sobolev_path": "--sobolev-path",
                "sobolev_balance": "--sobolev-balance"}


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
    return spec


def _train_opts(group: dict) -> str:
    opts = []
    for k, v in (group.get("train") or {}).items():
        if k not in _TRAIN_FLAGS:
            raise SdpError(f"unknown train option {k!r} in experiment; known: {', '.join(_TRAIN_FLAGS)}")
        if isinstance(v, bool):   # switches: --name / --no-name
            opts.append(_TRAIN_FLAGS[k] if v else _TRAIN_FLAGS[k].replace("--", "--no-", 1))
        else:
            opts.append(f"{_TRAIN_FLAGS[k]} {v}")
    return " ".join(opts)


def check_group(name: str, gi: int, raw: dict) -> dict:
    """Group ``gi`` of experiment ``name`` with the defaults filled in (``SdpError`` on unknown keys)."""
    if not isinstance(raw, dict):
        raise SdpError(f"experiment {name!r}, group {gi}: expected a mapping, got {raw!r}")
    unknown = set(raw) - set(GROUP_DEFAULTS) - {"task"}
    if unknown:
        raise SdpError(f"experiment {name!r}, group {gi}: unknown keys {sorted(unknown)}")
    if "task" not in raw:
        raise SdpError(f"experiment {name!r}, group {gi}: 'task' is required")
    return {**GROUP_DEFAULTS, **raw}


def expand(name: str, spec: dict, per_step: bool = False) -> dict:
    """Stage dictionaries for ``dvc.yaml`` (see module docstring). With ``runner: group`` in the
    experiment file, one ``group`` entry (every run through ``sdp pipeline NAME --run``, see
    :mod:`sdp_cli.runner`) and empty per-step lists, unless ``per_step`` (the per-step lists of
    any experiment: what ``--estimate`` sizes)."""
    out = {"collect_first": {}, "collect_next": {}, "train_first": {}, "train_next": {}, "evaluate": {},
           "group": {}}
    runner = spec.get("runner", "stages")
    if runner not in RUNNERS:
        raise SdpError(f"experiment {name!r}: runner must be one of {', '.join(RUNNERS)}, got {runner!r}")
    if runner == "group" and not per_step:
        loop_configs(name, spec)   # validates every run now, not hours into `dvc repro`
        out["group"][name] = {"experiment": name, "dir": f"runs/{name}"}
        return out
    for gi, raw in enumerate(spec["groups"]):
        g = check_group(name, gi, raw)
        t_a_opt = f"--t-a {g['t_a']}" if g["t_a"] is not None else ""
        k_opt = f"--k-rollout {g['k_rollout']}" if g["k_rollout"] is not None else ""
        train_opts = _train_opts(g)
        eval_t_a = g["eval_t_a"] or [g["t_a"]]
        for method, seed, n_traj in itertools.product(g["methods"], g["seeds"], g["n_traj"]):
            run = run_name(g["task"], method, n_traj, seed)
            base = f"runs/{name}/{run}"
            for k in range(g["n_algo"]):
                d = f"{base}/it{k}"
                key = f"{run}-it{k}"
                coll = {"task": g["task"], "n_traj": n_traj, "seed": 1000 * seed + k, "max_iter": g["max_iter"],
                        "dir": d}
                data = f"{d}/data.npz"
                save_at = ",".join(str(e) for e in g["save_at"] if e < g["epochs"])
                tr = {"method": method, "epochs": g["epochs"], "seed": seed, "horizon": g["horizon"],
                      "save_at": f"--save-at {save_at}" if save_at else "", "opts": train_opts, "dir": d,
                      "data": data}
                if k == 0:
                    # the naive-guess collection does not depend on the method: shared by all runs
                    dkey = f"{g['task']}-n{n_traj}-s{seed}"
                    tr["data"] = f"runs/{name}/data/{dkey}/data.npz"
                    out["collect_first"][dkey] = {**coll, "dir": f"runs/{name}/data/{dkey}"}
                    out["train_first"][key] = tr
                else:
                    prev = f"{base}/it{k - 1}/policy"
                    out["collect_next"][key] = {**coll, "prev": prev, "rollout_opts": f"{t_a_opt} {k_opt}".strip()}
                    out["train_next"][key] = {**tr, "prev": prev}
                ckpts = [(g["epochs"], "checkpoint.pt")] + [(e, f"epoch_{e}.pt") for e in g["save_at"]
                                                            if e < g["epochs"]]
                t_as = list(eval_t_a)
                if k == g["n_algo"] - 1:
                    t_as += [t for t in g["eval_t_a_last"] if t not in t_as]
                for (epochs, ck), t_a in itertools.product(ckpts, t_as):
                    ta = "default" if t_a is None else t_a
                    ekey = f"{key}-e{epochs}-ta{ta}"
                    tags = (f"--tag experiment={name} --tag run={run} --tag iteration={k} "
                            f"--tag group={gi}")
                    out["evaluate"][ekey] = {
                        "policy": f"{d}/policy", "ckpt": f"{d}/policy/{ck}", "n_test": g["n_test"],
                        "test_seed": g["test_seed"], "t_a": "" if t_a is None else f"--t-a {t_a}",
                        "k_rollout": k_opt, "max_iter": g["max_iter"], "dir": f"{d}/eval/e{epochs}-ta{ta}",
                        "refine_opts": "--single-shooting" if g["single_shooting"] else "", "tags": tags}
    return out  # empty dictionaries are fine: DVC's foreach then generates no stage


def run_name(task: str, method: str, n_traj: int, seed: int) -> str:
    """The folder of one run (the same name as the DVC stages' run folders)."""
    return f"{task}-{method}-n{n_traj}-s{seed}"


def loop_configs(name: str, spec: dict) -> dict[str, "LoopConfig"]:
    """``{run name: LoopConfig}`` of every run of an experiment (see :mod:`sdp_cli.pipeline`)."""
    from sdp_cli.loop import LoopConfig

    runs = {}
    for gi, raw in enumerate(spec["groups"]):
        g = check_group(name, gi, raw)
        for method, seed, n_traj in itertools.product(g["methods"], g["seeds"], g["n_traj"]):
            key = run_name(g["task"], method, n_traj, seed)
            if key in runs:
                raise SdpError(f"experiment {name!r}: run {key} appears in two groups")
            runs[key] = LoopConfig(
                task=g["task"], method=method, n_algo=g["n_algo"], n_traj=(int(n_traj),), epochs=g["epochs"],
                seed=seed, horizon=g["horizon"], t_a=g["t_a"], eval_t_a=tuple(g["eval_t_a"]),
                eval_t_a_last=tuple(g["eval_t_a_last"]), k_rollout=g["k_rollout"], n_test=g["n_test"],
                test_seed=g["test_seed"], max_iter=g["max_iter"], workers=1, device="cpu",
                train_options=dict(g["train"] or {}), single_shooting=g["single_shooting"],
                save_at=tuple(int(e) for e in g["save_at"] if e < g["epochs"]))
    return runs


def select_experiment(name: str, params_path: Path = Path("params.yaml"), root: Path = Path(".")) -> dict:
    """Expand experiment ``name`` and write it into ``params.yaml``; returns the stage counts."""
    spec = load_experiment(name, root)
    stages = expand(name, spec)
    params = {}
    if params_path.exists():
        params = yaml.safe_load(params_path.read_text()) or {}
    params["experiment"] = name
    params["experiment_stages"] = stages
    header = ("# Selected experiment and its generated stage lists. Written by `sdp pipeline NAME`\n"
              "# from pipelines/NAME.yaml: edit the experiment file, then re-run `sdp pipeline NAME`.\n")
    from sdp_cli.data.artifacts import atomic_write_bytes

    atomic_write_bytes(params_path, lambda f: f.write((header + yaml.safe_dump(params, sort_keys=False)).encode()))
    return {k: len(v) for k, v in stages.items()}

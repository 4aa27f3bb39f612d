"""``sdp evaluate``: one tidy row per run from a rollout artifact and its refinement.

Columns: method, task, n_traj, epochs, t_a, k_rollout, horizon (T_h), seed, n, mean/median policy cost,
success rate (reached the goal without diverging), divergences, max constraint violation, the share of
rollouts violating a constraint (``violation_rate``, and per constraint group, e.g.
``obstacles_violation_rate``) and the median final distance to the goal,
the paper's *refined* metrics (``refined_*``: TO warm-started by the policy rollout, cost over
its converged instances, convergence rate, iterations, solve time), ``argmin_cost_mean``
(ArgminCost of refined and TO alone, <= TO alone by construction, shown only beside the
others), ``policy_wins`` / ``policy_ties`` (instances where the policy guess beat TO alone, or reached
the same optimum: ArgminCost keeps the policy's solve on both, only the first says anything),
TO-alone cost (naive guess), convergence rate, iterations and solve time, rollout time;
with ``sdp refine --single-shooting``, the same for the single-shooting baseline (``ss_to_alone_*``
from the naive controls, ``ss_refined_*`` from the policy's controls). Written as CSV so that
``sdp report`` can aggregate across seeds.

Manifest: next to the CSV, ``<stem>.manifest.json`` names what each row was computed from
(rollouts, refined, the policy checkpoint, its training dataset; paths relative to the manifest),
with the run, iteration, method, seed, T_a, epochs and the code revision: ``sdp report`` finds
evaluations through their manifests and opens only the files they name.

Times are read from the artifacts' timing sidecars (:func:`sdp_cli.data.artifacts.load_timing`;
NaN when missing) and written to the CSV's timing sidecar (``eval.timing.json``: the timing
columns, one record per row), so that the CSV, the manifest and the metrics JSON hold no clock
readings; :func:`read_evaluation` joins them back.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import math

import numpy as np
import pandas as pd

from sdp_cli.families import DEFAULT_TO
from sdp_cli.algorithm.argmin import policy_outcomes
from sdp_cli.data.artifacts import (atomic_write_bytes, file_sha256, json_default, load_meta, load_npz, load_timing,
                                    resolve_recorded, save_timing, timing_path)
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.data.artifacts import artifact_writes, code_revision


def _mean(a) -> float:
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


#: manifest file of an evaluation CSV (``eval.csv`` -> ``eval.manifest.json``) and the files it names
MANIFEST_SUFFIX = ".manifest.json"
#: the manifest format of this code's evaluations (:mod:`sdp_cli.migrate` brings older ones to it)
LAYOUT = 2
ARTIFACT_KEYS = ("rollouts", "refined", "policy", "data")
#: constraint violation above which a rollout counts as violating (the optimizer's feasibility tolerance)
VIOLATION_TOL = 1e-6


def is_timing_column(name: str) -> bool:
    """Columns holding clock readings (``rollout_time``, ``*_solve_time_mean``, ...)."""
    return "_time" in name


def _timed(arrays: dict, timing: dict, key: str, n: int) -> np.ndarray:
    """A per-instance time: from the sidecar (or, for older artifacts, the arrays); NaN if unknown."""
    v = arrays.get(key, timing.get(key))
    v = np.asarray(v if v is not None else np.full(n, np.nan), dtype=float)
    return v if v.shape == (n,) else np.full(n, np.nan)


def _rollout_task(meta: dict):
    """The task a rollout artifact names, to recompute what older rollouts did not store."""
    return get_task(meta.get("task"), **(meta.get("task_options") or {}))


def group_violation_rates(r: dict, meta: dict) -> dict[str, float]:
    """``<group>_violation_rate`` per constraint group (``controls``, ``floor_ceiling``, ``obstacles``, ...):
    the share of rollouts breaking that group beyond :data:`VIOLATION_TOL` (diverged ones count as breaking).
    From the rollout's ``violation_<group>`` arrays, or, for rollouts written before those existed,
    recomputed from its ``X``, ``U`` and ``xi`` with the task it names."""
    arrays = {k[len("violation_"):]: np.asarray(v, float) for k, v in r.items() if k.startswith("violation_")}
    if not arrays and all(k in r for k in ("X", "U", "xi")):
        arrays = _rollout_task(meta).violations_per_instance(r["X"], r["U"], r["xi"])
    return {f"{g}_violation_rate": float(np.mean(~(v <= VIOLATION_TOL))) for g, v in arrays.items()}


def terminal_cost_mean(r: dict, meta: dict) -> dict[str, float]:
    """``terminal_cost_mean``: the mean over instances of the cost's terminal term ``l_T(x_T)`` (the part of
    ``policy_cost_mean`` that the final state alone makes; inf when a rollout diverged). From the rollout's
    ``terminal_cost`` array, or, for rollouts written before it existed, recomputed from ``X`` and ``xi`` with
    the task it names ({} when neither is there)."""
    if "terminal_cost" in r:
        v = np.asarray(r["terminal_cost"], float)
    elif all(k in r for k in ("X", "xi")):
        v = _rollout_task(meta).terminal_costs(r["X"], r["xi"])
    else:
        return {}
    return {"terminal_cost_mean": float(np.mean(v)) if np.all(np.isfinite(v)) else float("inf")}


def _solved_and_reached(rmeta: dict, d: dict, guess: str, ok: np.ndarray) -> float:
    """Share of instances whose solve from ``guess`` ("pol" or "base") converged and ends within the task's goal
    tolerance (NaN for an artifact without the per-instance trajectories)."""
    key = f"inst_{guess}_X"
    if key not in d or not ok.any():
        return float(np.mean(ok)) if key in d else float("nan")

    task = get_task(rmeta["task"], **(rmeta.get("task_options") or {}))
    X, xi = d[key], d["inst_xi"]
    reached = [bool(ok[i]) and task.goal_distance(X[i, -1], xi[i]) <= task.goal_tolerance for i in range(len(X))]
    return float(np.mean(reached))


def _conversion_before_the_setting(rmeta: dict, pcfg: dict) -> str | None:
    """The conversion of a rollout made before it was recorded: inverse dynamics for a chunked policy with
    state actions, none for torques (MLPs, torque chunks)."""
    if rmeta["config"].get("k_rollout") is None:
        return None

    try:
        action = (pcfg.get("policy") or {}).get("action") or get_task(rmeta.get("task"),
                                                                      **(rmeta.get("task_options") or {})).action
    except SdpError:   # a task no longer registered: the row keeps an empty conversion
        return None
    return "inverse-dynamics" if action != "u" else None


def evaluation_row(rollouts: str | os.PathLike, refined: str | os.PathLike | None = None,
                   extra: dict | None = None) -> dict:
    """The summary of one run (a dict of scalars)."""
    r, rmeta = load_npz(rollouts, kind="rollout")
    missing = [k for k in ("cost", "reached", "diverged", "max_violation") if k not in r]
    if missing or not isinstance(rmeta.get("config"), dict):
        raise SdpError(f"corrupt rollout artifact {rollouts}: missing {', '.join(missing) or 'config'}")
    pcfg = rmeta.get("policy_config", {}) or {}
    # checkpoint format 2 nests the config by section; format 1 was flat, with T_h (sdp_cli.policy.config)
    horizon = (pcfg.get("policy") or {}).get("horizon", pcfg.get("T_h"))
    cost = np.asarray(r["cost"], float)
    row = {
        "task": rmeta.get("task"), "method": rmeta.get("method"),
        "n_traj": (rmeta.get("policy_dataset") or {}).get("n_traj"), "epochs": rmeta.get("policy_epoch"),
        "t_a": rmeta["config"].get("t_a"), "k_rollout": rmeta["config"].get("k_rollout"),
        # predicted chunk -> controls (sdp_cli.tasks.conversion): state-action policies only (empty for torques);
        # their rollouts made before the setting existed used inverse dynamics
        "conversion": (rmeta["config"]["conversion"] if "conversion" in rmeta["config"]
                       else _conversion_before_the_setting(rmeta, pcfg)),
        "horizon": horizon, "train_seed": pcfg.get("seed"), "test_seed": rmeta["config"].get("seed"),
        # trained with the network compiled (TrainConfig.compile: other numerics than eager at float32 rounding)
        "compiled": bool(pcfg.get("compile", False)), "n": len(cost),
        "policy_cost_mean": float(np.mean(cost)) if np.all(np.isfinite(cost)) else float("inf"),
        "policy_cost_median": float(np.median(cost)),
        **terminal_cost_mean(r, rmeta),
        "success_rate": float(np.mean(r["reached"])),
        "diverged": int(np.sum(r["diverged"])),
        "max_violation": float(np.max(np.where(np.isfinite(r["max_violation"]), r["max_violation"], np.inf))),
        # share of rollouts that break a constraint (an obstacle, the floor or ceiling) beyond the solver's
        # feasibility tolerance; diverged rollouts count as violating
        "violation_rate": float(np.mean(~(np.asarray(r["max_violation"], float) <= VIOLATION_TOL))),
        **group_violation_rates(r, rmeta),
        "goal_distance_median": (float(np.nanmedian(r["goal_distance"]))
                                 if "goal_distance" in r and np.isfinite(r["goal_distance"]).any() else float("nan")),
        "rollout_time": float(r.get("rollout_time", load_timing(rollouts).get("rollout_time", np.nan))),
    }
    row["rollout_time_per_instance"] = row["rollout_time"] / len(cost)
    if refined is not None:
        d, dmeta = load_npz(refined, kind="dataset")
        inst = ("inst_pol_converged", "inst_base_converged", "inst_pol_iterations", "inst_base_iterations",
                "inst_pol_cost", "inst_base_cost")
        if "inst_winner" in d and any(k not in d for k in inst):
            raise SdpError(f"corrupt refine artifact {refined}: missing per-instance records")
        if "inst_winner" not in d:
            raise SdpError(f"{refined} is not the output of `sdp refine` (no per-instance records)")
        want = (dmeta.get("config") or {}).get("rollouts_sha256")
        if want is not None and want != file_sha256(rollouts):
            raise SdpError(f"{refined} refines another rollout artifact ({dmeta['config'].get('rollouts')}), "
                           f"not {rollouts}")
        if len(d["inst_winner"]) != len(cost):
            raise SdpError(f"{refined} refines {len(d['inst_winner'])} instances, {rollouts} has {len(cost)}")
        dt, m = load_timing(refined), len(cost)
        pol_ok, base_ok = d["inst_pol_converged"].astype(bool), d["inst_base_converged"].astype(bool)
        tried = d["inst_pol_iterations"] >= 0
        wins, ties = policy_outcomes(d["inst_winner"], d["inst_pol_cost"], d["inst_base_cost"], base_ok)
        best = np.where(d["inst_winner"] == 0, d["inst_pol_cost"],
                        np.where(d["inst_winner"] == 1, d["inst_base_cost"], np.nan))
        row.update({
            # the TO family of the refinement and of TO alone (sdp_cli.trajopt.TO_FAMILIES; before --to: ms)
            "to": (dmeta.get("config") or {}).get("to", DEFAULT_TO),
            # the paper's "refined": TO warm-started by the policy's rollout (Algorithm 1 line 7)
            "refined_cost_mean": _mean(np.where(pol_ok, d["inst_pol_cost"], np.nan)),
            "refined_converged_rate": float(np.mean(pol_ok)),
            # over the instances solved from the policy guess (a diverged rollout is no guess)
            "refined_solved_rate": float(np.mean(tried)),
            "refined_iterations_mean": _mean(np.where(tried, d["inst_pol_iterations"], np.nan)),
            "refined_solve_time_mean": _mean(np.where(tried, _timed(d, dt, "inst_pol_time", m), np.nan)),
            # ArgminCost(refined, TO alone): <= TO alone by construction, not evidence of anything alone
            "argmin_cost_mean": _mean(best),
            "argmin_converged_rate": float(np.mean(d["inst_winner"] >= 0)),
            # strict wins; ties (both guesses reach one optimum) are kept from the policy but are no win
            "policy_wins": wins,
            "policy_ties": ties,
            "to_alone_cost_mean": _mean(np.where(base_ok, d["inst_base_cost"], np.nan)),
            "to_alone_converged_rate": float(np.mean(base_ok)) if np.any(d["inst_base_iterations"] >= 0) else float("nan"),
            "to_alone_iterations_mean": _mean(np.where(d["inst_base_iterations"] >= 0, d["inst_base_iterations"], np.nan)),
            "to_alone_solve_time_mean": _mean(np.where(d["inst_base_iterations"] >= 0, _timed(d, dt, "inst_base_time", m), np.nan)),
            # the task's success for the TO solutions too: converged and within the goal tolerance at T
            "refined_success_rate": _solved_and_reached(rmeta, d, "pol", pol_ok),
            "to_alone_success_rate": _solved_and_reached(rmeta, d, "base", base_ok),
        })
        if "inst_ss_base_converged" in d:   # the single-shooting baseline (sdp refine --single-shooting)
            for g, name in (("base", "ss_to_alone"), ("pol", "ss_refined")):
                ok, tried = d[f"inst_ss_{g}_converged"].astype(bool), d[f"inst_ss_{g}_iterations"] >= 0
                row.update({
                    f"{name}_cost_mean": _mean(np.where(ok, d[f"inst_ss_{g}_cost"], np.nan)),
                    f"{name}_converged_rate": float(np.mean(ok)) if tried.any() else float("nan"),
                    f"{name}_iterations_mean": _mean(np.where(tried, d[f"inst_ss_{g}_iterations"], np.nan)),
                    f"{name}_solve_time_mean": _mean(np.where(tried, _timed(d, dt, f"inst_ss_{g}_time", m), np.nan))})
    row.update(extra or {})
    return row


def write_metrics(row: dict, out: str | os.PathLike) -> Path:
    """The row without its timing columns as a JSON object (DVC metrics file); non-finite
    numbers become null."""
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()
             if not is_timing_column(k)}
    return atomic_write_bytes(out, lambda f: f.write(json.dumps(clean, indent=2, default=str).encode()))


def evaluation_artifacts(rollouts: str | os.PathLike, refined: str | os.PathLike | None = None) -> dict:
    """The files an evaluation row comes from, as absolute paths (None where unknown): the
    rollouts, their refinement, the policy checkpoint that made them and its training dataset;
    ``git_rev``: the code revision recorded in the rollouts (and the refinement's when it differs,
    ``rollouts_rev+refined_rev``), i.e. the code that computed the row, not the one that wrote it."""
    meta = load_meta(rollouts, kind="rollout")

    def existing(p):
        return str(Path(p).resolve()) if p and Path(p).exists() else None

    revs = [(meta.get("provenance") or {}).get("git_rev") or "unknown"]
    if refined is not None and Path(refined).exists():
        rmeta = load_meta(refined, kind="dataset")
        rrev = (rmeta.get("provenance") or {}).get("git_rev") or "unknown"
        revs += [rrev] if rrev != revs[0] else []
    return {"rollouts": existing(rollouts), "refined": existing(refined),
            "policy": existing(_recorded_policy((meta.get("config") or {}).get("policy"), Path(rollouts).parent)),
            "data": existing(resolve_recorded((meta.get("policy_dataset") or {}).get("path"), Path(rollouts).parent)),
            "git_rev": "+".join(revs)}


def _recorded_policy(path: str | None, folder: Path) -> Path | None:
    """A rollout's recorded policy: relative to the rollout's folder, or (rollouts written before
    that) absolute or relative to the folder `sdp rollout` ran in."""
    if not path:
        return None
    here = resolve_recorded(path, folder)
    return here if here.exists() or Path(path).is_absolute() else Path(path)


def manifest_path(csv: str | os.PathLike) -> Path:
    """``eval.csv`` -> ``eval.manifest.json`` (next to it)."""
    p = Path(csv)
    return p.with_name(p.stem + MANIFEST_SUFFIX)


def files_named(root: str | os.PathLike, match) -> list[Path]:
    """Files under ``root`` whose name satisfies ``match``, sorted. Unlike ``Path.rglob`` (Python < 3.13) it
    follows symlinked folders, so a runs folder assembled with ``ln -s`` from several places is read whole;
    each real folder is walked once (a link to an ancestor does not loop, a link beside its target does not
    count a file twice)."""
    found, seen = [], set()
    for top, dirs, files in os.walk(root, followlinks=True):
        real = os.path.realpath(top)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort()
        found += [Path(top) / f for f in files if match(f)]
    return sorted(found)


def find_manifests(root: str | os.PathLike) -> list[Path]:
    """Every evaluation manifest under ``root`` (:func:`files_named`: symlinked folders followed)."""
    return files_named(root, lambda name: name.endswith(MANIFEST_SUFFIX))


def write_evaluation(rows: list[dict], out: str | os.PathLike, artifacts: list[dict] | None = None,
                     wall_time: float | None = None, wall_partial: bool = False) -> Path:
    """Write rows as CSV atomically, their timing columns to the CSV's timing sidecar (with ``wall_time``, the
    measured seconds of the whole evaluation, when given), and the manifest of ``artifacts`` (one
    :func:`evaluation_artifacts` per row) next to it."""
    with artifact_writes():   # the CSV, its timing sidecar and its manifest: all three or none
        return _write_evaluation(rows, Path(out), artifacts, wall_time, wall_partial)


def _write_evaluation(rows, out: Path, artifacts, wall_time, wall_partial) -> Path:
    df = pd.DataFrame(rows)
    timed = [c for c in df.columns if is_timing_column(c)]
    path = atomic_write_bytes(out, lambda f: f.write(df.drop(columns=timed).to_csv(index=False).encode()))
    save_timing(out, {"rows": df[timed].astype(float).to_dict("records"),
                      **({"wall_time": float(wall_time), "wall_partial": bool(wall_partial)}
                         if wall_time is not None else {})})
    if artifacts is not None:
        if len(artifacts) != len(rows):
            raise SdpError(f"{len(rows)} evaluation rows but {len(artifacts)} artifact records")
        folder = out.resolve().parent
        entries = []
        for i, (row, art) in enumerate(zip(rows, artifacts)):
            rel = {k: (os.path.relpath(v, folder) if v else None) if k in ARTIFACT_KEYS else v for k, v in art.items()}
            entries.append({"row": i, "run": row.get("run"), "iteration": int(row.get("iteration") or 0),
                            "method": row.get("method"), "task": row.get("task"), "seed": row.get("train_seed"),
                            "t_a": row.get("t_a"), "epochs": row.get("epochs"), **rel})
            # the code that computed the row (from its artifacts; this code where they record none)
            entries[-1]["git_rev"] = str(entries[-1].get("git_rev") or code_revision())
        revs = sorted({e["git_rev"] for e in entries}) or [code_revision()]
        man = {"format": "sdp-evaluation-manifest", "format_version": LAYOUT, "eval": out.name,
               "git_rev": revs[0] if len(revs) == 1 else ",".join(revs), "entries": entries}
        text = json.dumps(man, indent=1, default=json_default).encode()
        atomic_write_bytes(manifest_path(out), lambda f: f.write(text))
    return path


def read_manifest(path: str | os.PathLike) -> dict:
    """A manifest with its paths made absolute; ``SdpError`` if it is unreadable or names no CSV."""
    path = Path(path)
    try:
        man = json.loads(path.read_text())
        entries, name = man["entries"], man["eval"]
        folder = path.resolve().parent
        for e in entries:
            for k in ARTIFACT_KEYS:
                e[k] = str((folder / e[k]).resolve()) if e.get(k) else None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SdpError(f"corrupt evaluation manifest {path}: {e}") from None
    man["eval"] = str(folder / name)
    return man


def read_evaluation(path: str | os.PathLike) -> pd.DataFrame:
    """An ``eval.csv`` joined with the timing columns of its sidecar (when it has one record
    per row; otherwise without them)."""
    df = pd.read_csv(path)
    timed = load_timing(path).get("rows")
    if isinstance(timed, list) and len(timed) == len(df) and timing_path(path).is_file():
        t = pd.DataFrame(timed, index=df.index)
        df = pd.concat([df, t[[c for c in t.columns if c not in df]]], axis=1)
    return df

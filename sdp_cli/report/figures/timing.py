"""Where the time of a loop goes: ``timing_<task>`` (CSV + markdown), one row per run and iteration.

Columns (seconds of wall time, from the timing sidecars of the files the evaluation manifests name):

- ``collect_solve_s``: TO solves of the policy's training dataset (``attempts x mean_solve_time``);
  ``collect_wall_s``: the whole collection (optimizer compilation or loading, warm-starting
  rollouts, solves, writing). A dataset shared by several runs (iteration 0 of the DVC layout)
  counts for each of them;
- ``train_steps`` (the run folder's ``metrics.csv``), ``train_s`` (its timing sidecar, carried
  across resumes), ``train_s_per_step``;
- ``eval_rollout_s`` and ``eval_solve_s``: rollouts of the test set and the TO solves of its
  refinement (policy guess + TO alone), summed over the T_a values and checkpoints evaluated at
  that iteration (``eval_t_a_values``, e.g. "1,4,8"); ``eval_ss_solve_s``: the single-shooting
  baseline's solves (from the policy's and the naive controls) where the loop ran it (fig2: about
  19 s an evaluation); ``eval_wall_s``: the evaluation's measured wall time (rollouts, every solve,
  compilation, writing; recorded by ``sdp loop`` since results version 2; NaN before, and where a
  resumed evaluation found part of its work done, so measured only the rest);
- ``total_s``: collection wall + training + the evaluation's measured wall time (where it was not
  measured, the sum of its parts, flagged by ``total_measured`` False).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.data.artifacts import load_timing
from sdp_cli.report.figures.style import save_csv, save_md


def _policy_dir(policy) -> Path | None:
    """The run folder of a policy checkpoint the manifest names (a folder or a ``.pt`` in it)."""
    if not isinstance(policy, str) or not policy:
        return None
    p = Path(policy)
    return p if p.is_dir() else p.parent


def _collect_seconds(data) -> tuple[float, float]:
    """(solver seconds, wall seconds) of a dataset's collection; NaN where unknown."""
    if not isinstance(data, str) or not data:
        return float("nan"), float("nan")
    t = load_timing(data)
    return (float(t.get("attempts", np.nan)) * float(t.get("mean_solve_time", np.nan)),
            float(t.get("wall_time", np.nan)))


def _train(run_dir: Path) -> tuple[float, float]:
    """(training steps, wall seconds): the steps from ``metrics.csv``, the time from the run
    folder's timing sidecar (``policy.timing.json``)."""
    m = run_dir / "metrics.csv"
    if not m.is_file():
        return float("nan"), float("nan")
    df = pd.read_csv(m)
    steps = float(df.step.iloc[-1]) if len(df) else float("nan")
    return steps, float(load_timing(run_dir).get("wall_time", np.nan))


def _eval_wall(g: pd.DataFrame) -> float:
    """The measured wall seconds of the evaluations these rows come from (their ``eval.csv`` sidecars)."""
    if "source" not in g:
        return float("nan")
    recs = [load_timing(Path(str(s)) / "eval.csv") for s in g["source"].dropna().unique()]
    walls = [r.get("wall_time", np.nan) if not r.get("wall_partial") else np.nan for r in recs]
    return float(np.sum(walls)) if walls and np.all(np.isfinite(walls)) else float("nan")


def _col(g: pd.DataFrame, name: str, default: float) -> pd.Series:
    return g[name].astype(float).fillna(default) if name in g else pd.Series(default, index=g.index)


def timing_table(df: pd.DataFrame, task: str) -> pd.DataFrame:
    d = df[df.task == task]
    rows = []
    d = d.assign(_run_dir=d["policy"].map(lambda p: str(_policy_dir(p))))
    for (method, seed, it, run_dir), g in d.groupby(["method", "train_seed", "iteration", "_run_dir"]):
        if run_dir == "None":
            continue
        steps, train_s = _train(Path(run_dir))
        n = g["n"].astype(float)
        # mean over the instances solved from a guess x their number (older rows: mean over all, rate 1)
        solve = (_col(g, "refined_solve_time_mean", 0.0) * n * _col(g, "refined_solved_rate", 1.0)
                 + _col(g, "to_alone_solve_time_mean", 0.0) * n)
        ss = sum(_col(g, f"{name}_solve_time_mean", 0.0) * n for name in ("ss_refined", "ss_to_alone"))
        c_solve, c_wall = _collect_seconds(g["data"].iloc[0])
        row = {"method": method, "run": g.run.iloc[0], "train_seed": int(seed), "iteration": int(it),
               "collect_solve_s": c_solve, "collect_wall_s": c_wall, "train_steps": steps, "train_s": train_s,
               "train_s_per_step": train_s / steps if steps else np.nan,
               "eval_t_a_values": ",".join(str(int(t)) for t in sorted(g.t_a.dropna().unique())),
               "eval_rollout_s": float(g.rollout_time.sum()),
               "eval_solve_s": float(np.sum(solve)), "eval_ss_solve_s": float(np.sum(ss)),
               "eval_wall_s": _eval_wall(g)}
        collect = c_wall if np.isfinite(c_wall) else c_solve
        measured = np.isfinite(row["eval_wall_s"])
        evaluation = row["eval_wall_s"] if measured else np.nansum([row["eval_rollout_s"], row["eval_solve_s"],
                                                                    row["eval_ss_solve_s"]])
        row["total_s"] = float(np.nansum([collect, train_s, evaluation]))
        row["total_measured"] = bool(measured and np.isfinite(c_wall) and np.isfinite(train_s))
        rows.append(row)
    return pd.DataFrame(rows).sort_values(["method", "train_seed", "iteration"]) if rows else pd.DataFrame()


def timing(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """``timing_<task>``: collection, training and evaluation seconds per run and iteration (``carried``:
    the earlier report's rows of runs whose files are gone, :class:`~sdp_cli.report.carry.Carried`)."""
    tab = timing_table(df, task)
    d = df[df.task == task]
    old = carried.rows(f"timing_{task}.csv", task, d) if carried else pd.DataFrame()
    if not old.empty:
        tab = pd.concat([tab, old], ignore_index=True).sort_values(["method", "train_seed", "iteration"], kind="stable")
    if tab.empty:
        return []
    return [save_csv(tab, out / f"timing_{task}.csv"),
            save_md(tab, out / f"timing_{task}.md", f"Where the time goes — {task} (wall seconds)")]

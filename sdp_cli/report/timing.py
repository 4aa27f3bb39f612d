"""Where the time of a loop goes: ``timing_<task>`` (CSV + markdown), one row per run and iteration.

Columns (seconds of wall time, from the artifacts themselves):

- ``collect_solve_s``: TO solves of the collection (``attempts x mean_solve_time`` of the
  dataset's stats); ``collect_wall_s``: the whole collection stage (optimizer compilation or
  loading, warm-starting rollouts, solves, writing), where the dataset records it;
- ``train_steps``, ``train_s`` (the run's ``metrics.csv`` wall time, carried across resumes),
  ``train_s_per_step``;
- ``eval_rollout_s`` and ``eval_solve_s``: rollouts of the test set and the TO solves of its
  refinement (policy guess + TO alone), summed over the T_a values evaluated at that iteration
  (``eval_t_a_values``, e.g. "1,4,8");
- ``total_s``: the sum.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.data.artifacts import load_timing
from sdp_cli.report.runs import ITERATION_DIR


def _iteration_dir(source: str) -> Path | None:
    for p in (Path(source), *Path(source).parents):
        if ITERATION_DIR.match(p.name):
            return p
    return None


def _collect_seconds(it_dir: Path) -> tuple[float, float]:
    """(solver seconds, wall seconds) of an iteration's collection; NaN where unknown."""
    data = it_dir / "data.npz"
    if not data.is_file():  # DVC layout: the naive-guess dataset of iteration 0 is shared elsewhere
        return float("nan"), float("nan")
    t = load_timing(data)
    return (float(t.get("attempts", np.nan)) * float(t.get("mean_solve_time", np.nan)),
            float(t.get("wall_time", np.nan)))


def _train(it_dir: Path) -> tuple[float, float]:
    """(training steps, wall seconds): the steps from ``metrics.csv``, the time from the run
    folder's timing sidecar (``policy.timing.json``)."""
    m = it_dir / "policy" / "metrics.csv"
    if not m.is_file():
        return float("nan"), float("nan")
    df = pd.read_csv(m)
    steps = float(df.step.iloc[-1]) if len(df) else float("nan")
    return steps, float(load_timing(it_dir / "policy").get("wall_time", np.nan))


def _col(g: pd.DataFrame, name: str, default: float) -> pd.Series:
    return g[name].astype(float).fillna(default) if name in g else pd.Series(default, index=g.index)


def timing_table(df: pd.DataFrame, task: str) -> pd.DataFrame:
    d = df[df.task == task]
    rows = []
    for (method, seed, it, source_dir), g in d.groupby(
            ["method", "train_seed", "iteration", d["source"].map(lambda s: str(_iteration_dir(s)))]):
        it_dir = _iteration_dir(g.source.iloc[0])
        if it_dir is None:
            continue
        steps, train_s = _train(it_dir)
        n = g["n"].astype(float)
        # mean over the instances solved from a guess x their number (older rows: mean over all, rate 1)
        solve = (_col(g, "refined_solve_time_mean", 0.0) * n * _col(g, "refined_solved_rate", 1.0)
                 + _col(g, "to_alone_solve_time_mean", 0.0) * n)
        c_solve, c_wall = _collect_seconds(it_dir)
        row = {"method": method, "train_seed": int(seed), "iteration": int(it),
               "collect_solve_s": c_solve, "collect_wall_s": c_wall, "train_steps": steps, "train_s": train_s,
               "train_s_per_step": train_s / steps if steps else np.nan,
               "eval_t_a_values": ",".join(str(int(t)) for t in sorted(g.t_a.dropna().unique())),
               "eval_rollout_s": float(g.rollout_time.sum()),
               "eval_solve_s": float(np.sum(solve))}
        collect = c_wall if np.isfinite(c_wall) else c_solve
        row["total_s"] = float(np.nansum([collect, train_s, row["eval_rollout_s"], row["eval_solve_s"]]))
        rows.append(row)
    return pd.DataFrame(rows).sort_values(["method", "train_seed", "iteration"]) if rows else pd.DataFrame()

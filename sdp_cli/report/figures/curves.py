"""Data-series files for ``dvc plots``: training curves and the loop's costs, one CSV per series.

- ``curves/<run>-it<k>.csv``: the run's training metrics (``step, epoch, loss, dp, sobolev, lr``),
  thinned to at most ``MAX_ROWS`` rows (every n-th step, the last one kept) so that long runs stay
  small enough to commit;
- ``loop/<task>-<method>.csv``: per algorithm iteration, ``policy`` and ``refined`` mean costs and the
  policy's ``success`` rate, means over seeds at the loop's T_a (diverged means left empty).

``dvc.yaml`` declares them as top-level plots (``dvc plots show``, ``dvc plots diff``).
"""

from __future__ import annotations

from pathlib import Path
import json

import numpy as np
import pandas as pd

from sdp_cli.data.artifacts import atomic_write_bytes
from sdp_cli.report.figures.timing import _policy_dir

MAX_ROWS = 500
CURVE_FIELDS = ["step", "epoch", "loss", "dp", "sobolev", "lr"]


def _save(df: pd.DataFrame, path: Path) -> Path:
    return atomic_write_bytes(path, lambda f: f.write(df.to_csv(index=False).encode()))


def training_curves(df: pd.DataFrame, out: Path) -> list[Path]:
    """One thinned metrics CSV per trained policy that the evaluation manifests name."""
    written, done = [], set()
    for policy, run, it in df[["policy", "run", "iteration"]].drop_duplicates().itertuples(index=False):
        run_dir = _policy_dir(policy)
        m = run_dir / "metrics.csv" if run_dir is not None else None
        if m is None or not m.is_file() or m in done:
            continue
        done.add(m)
        curve = pd.read_csv(m)
        if curve.empty:
            continue
        keep = np.unique(np.r_[np.arange(0, len(curve), max(1, int(np.ceil(len(curve) / MAX_ROWS)))), len(curve) - 1])
        name = f"{run}-it{int(it)}.csv"
        written.append(_save(curve.iloc[keep][[c for c in CURVE_FIELDS if c in curve]], out / "curves" / name))
    return written


#: the columns of the metrics summary (``sdp report --metrics``), means over seeds
METRIC_COLUMNS = ("policy_cost_mean", "policy_cost_median", "success_rate", "refined_cost_mean",
                  "refined_converged_rate", "argmin_cost_mean", "to_alone_cost_mean", "to_alone_converged_rate")


def metrics_summary(loop_rows: pd.DataFrame) -> dict:
    """``{task: {method: {column: mean over seeds}}}`` at the last iteration, the largest epoch count
    and the loop's T_a (``loop_rows``), for ``dvc metrics show`` / ``dvc metrics diff`` (non-finite
    means are null)."""
    out: dict = {}
    for (task, method), g in loop_rows.groupby(["task", "method"]):
        g = g[g.iteration == g.iteration.max()]
        g = g[g.epochs == g.epochs.max()] if "epochs" in g and g.epochs.notna().any() else g
        vals = {c: float(g[c].astype(float).mean()) for c in METRIC_COLUMNS if c in g}
        vals = {c: (v if np.isfinite(v) else None) for c, v in vals.items()}
        out.setdefault(str(task), {})[str(method)] = {"iteration": int(g.iteration.max()), "seeds": int(g.train_seed.nunique()),
                                                      **vals}
    return out


def write_metrics(summary: dict, path: Path) -> Path:
    return atomic_write_bytes(path, lambda f: f.write(json.dumps(summary, indent=2, sort_keys=True).encode()))


def loop_costs(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """``loop/<task>-<method>.csv``, x = iteration, at the loop's T_a (:func:`~sdp_cli.report.rows.loop_t_a`)."""
    from sdp_cli.report.rows import loop_t_a

    loop_rows = loop_t_a(df[df.task == task])
    cols = {"policy_cost_mean": "policy", "refined_cost_mean": "refined", "success_rate": "success"}
    written = []
    for method, g in loop_rows.groupby("method"):
        m = g.groupby("iteration")[[c for c in cols if c in g]].mean().rename(columns=cols)
        m = m.replace([np.inf, -np.inf], np.nan).reset_index()
        written.append(_save(m, out / "loop" / f"{task}-{method}.csv"))
    return written

"""The rules every claim is judged by: a :class:`Row` per claim, numbers as ``mean ± ci (n seeds)``,
ratio claims by :func:`ratio_verdict`, "solves" at :data:`SOLVED` success, and a loop's final iteration
(:func:`_last`) with the runs that have not reached it named (:func:`_unfinished`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from sdp_cli.report.figures import _loop_t_a
from sdp_cli.report.runs import mean_ci

SOLVED = 0.5          #: success rate from which a policy "solves" a task
VERDICTS = ("reproduced", "partly", "not reproduced", "not run")


@dataclass
class Row:
    ours: str
    verdict: str
    detail: str = ""     # what was measured beyond the headline number (shown in the notes column)


def fmt(values, digits: int = 3, pct: bool = False, unit: str = "") -> str:
    """``mean ± ci (n seeds)`` of per-seed values."""
    m, h, n = mean_ci(pd.Series(values, dtype=float))
    if not np.isfinite(m):
        return "diverged" if np.isinf(m) else "n/a"
    f = (lambda v: f"{100 * v:.0f}%") if pct else (lambda v: f"{v:.{digits}g}{unit}")
    ci = f" ± {f(h)}" if np.isfinite(h) else ""
    return f"{f(m)}{ci} ({n} seed{'s' if n != 1 else ''})"


def ratio_verdict(r: float, paper: float) -> str:
    """Reproduced with at least half the paper's effect (r - 1), partly with at least a tenth of it."""
    if not np.isfinite(r):
        return "not reproduced"
    if r - 1 >= (paper - 1) / 2:
        return "reproduced"
    return "partly" if r - 1 >= (paper - 1) / 10 else "not reproduced"


def combine(verdicts: list[str]) -> str:
    """One verdict from several parts: reproduced if all are, not reproduced if all are not, else partly."""
    if verdicts and all(v == "reproduced" for v in verdicts):
        return "reproduced"
    return "not reproduced" if all(v == "not reproduced" for v in verdicts) else "partly"


def _final_iteration(d: pd.DataFrame) -> pd.Series:
    """Per task, its loops' final iteration: the last one its runs' ``n_algo`` asks for where the rows
    record it (a loop's rows do; older ones get it from the run's ``loop_config.json``), else the last
    one any of its runs reached."""
    reached = d.groupby("task").iteration.max()
    if "n_algo" not in d:
        return reached
    asked = (d.groupby("task").n_algo.max() - 1).reindex(reached.index)
    return pd.concat([reached, asked], axis=1).max(axis=1)


def _last(d: pd.DataFrame) -> pd.DataFrame:
    """The final loop iteration at the loop's T_a, of the runs that reached it (one row per task, method
    and seed); a task's final iteration is :func:`_final_iteration`'s."""
    if not len(d):
        return d
    d = pd.concat([_loop_t_a(g) for _, g in d.groupby("task")])
    return d[d.iteration == d.task.map(_final_iteration(d))]


def _unfinished(d: pd.DataFrame) -> str:
    """``"runs not finished (left out): ..."`` for runs that have not reached their task's final iteration."""
    if not len(d):
        return ""
    last = d.groupby(["task", "run"]).iteration.max()
    final = _final_iteration(d)
    todo = sorted(run for (task, run), it in last.items() if it < final[task])
    return f"runs not finished (left out): {', '.join(todo)}" if todo else ""


def _per_seed(d: pd.DataFrame, col: str) -> pd.Series:
    return d.groupby("train_seed")[col].mean()

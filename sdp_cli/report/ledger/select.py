"""What a check of the ledger reads: a report's rows, selected by the check's ``experiment``, ``method``,
``where`` and ``at`` (:class:`Selection`), grouped by its ``per`` columns, and how a column and a group are named
in the ledger's prose (:data:`COLUMNS`, :func:`group_label`). Which rows are a run's final ones is decided in
:mod:`sdp_cli.report.rows`; this module only picks among them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from sdp_cli.errors import SdpError
from sdp_cli.report.ledger.verdicts import fmt
from sdp_cli.report.rows import (conversion_text, final_iteration, last_iteration, loop_t_a, method_label,
                                per_seed)

#: ``at`` of a selection: which rows of a report a check reads
AT = {
    "last_iteration": "each loop's final iteration at the loop's T_a (runs partway left out)",
    "sweep": "each loop's final iteration at every T_a evaluated there (Table 2c's sweep)",
    "loop": "every iteration at the loop's T_a",
    "final_epochs": "each task and method at its largest number of epochs (Fig. 1's second n_pl)",
    "rows": "every row",
}

#: how the ledger names a report column: ``(words, unit)``; ``"%"`` prints a share as a percentage.
#: ``ss_`` columns are the single-shooting baseline's (the words gain "(single shooting)").
COLUMNS = {
    "policy_cost_mean": ("cost", ""), "success_rate": ("success", "%"),
    "goal_distance_median": ("final distance", " m"), "violation_rate": ("constraint violated", "%"),
    "obstacles_violation_rate": ("an obstacle hit", "%"), "refined_iterations_mean": ("TO iterations from the policy", ""),
    "to_alone_iterations_mean": ("TO iterations alone", ""), "refined_cost_mean": ("cost refined from the policy", ""),
    "to_alone_cost_mean": ("TO alone's cost", ""), "refined_solve_time_mean": ("refine", " s"),
    "to_alone_solve_time_mean": ("TO alone", " s"), "rollout_time_per_instance": ("rollout", " s"),
    "to_alone_converged_rate": ("TO alone converges", "%"), "refined_converged_rate": ("refine converges", "%"),
    "to_alone_success_rate": ("TO alone reaches the goal", "%"),
    "refined_success_rate": ("refined reaches the goal", "%"), "diverged": ("diverged rollouts", ""),
}

#: group columns as the ledger names them (``T_h 32``)
SHORT = {"horizon": "T_h", "t_a": "T_a", "k_rollout": "K"}


def column_text(col: str) -> tuple[str, str]:
    """``(words, unit)`` of a column (:data:`COLUMNS`); an unknown column is named as it is."""
    if col.startswith("ss_") and col[3:] in COLUMNS:
        words, unit = COLUMNS[col[3:]]
        return f"{words} (single shooting)", unit
    return COLUMNS.get(col, (col, ""))


def show(rows: pd.DataFrame, cols: list[str]) -> list[str]:
    """``["cost 30.7 ± 0.08 (5 seeds)", "final distance 0.08 m ± ..."]``: each of ``cols`` (those ``rows`` have, not
    all empty) as the mean over seeds with its interval."""
    out = []
    for c in cols:
        if c in rows and rows[c].notna().any():
            words, unit = column_text(c)
            out.append(f"{words} {fmt(per_seed(rows, c), pct=unit == '%', unit='' if unit == '%' else unit)}")
    return out


def value_text(col: str, v: float) -> str:
    """One number of column ``col``: ``"42%"``, ``"0.75 m"``, ``"30.2"``."""
    unit = column_text(col)[1]
    return f"{100 * v:.0f}%" if unit == "%" else f"{v:.3g}{unit}"


@dataclass(frozen=True)
class Selection:
    """The rows of one report a check reads. ``experiment``: the report (``fig2``; ``bench/train_step`` for a bench's
    CSV); ``method``: one method's rows (None: every method's); ``where``: ``{column: value}`` (a list: any of them;
    ``"min"``/``"max"``: the extreme value among the selected rows); ``at``: a key of :data:`AT`."""
    experiment: str
    method: str | None = None
    where: dict = field(default_factory=dict)
    at: str = "last_iteration"

    def report(self, res: dict) -> pd.DataFrame | None:
        return res.get(self.experiment)

    def rows(self, res: dict, method: str | None = "") -> pd.DataFrame:
        """The selected rows (``method``: another method's instead of :attr:`method`; None: every method's)."""
        d = res.get(self.experiment)
        if d is None or d.empty:
            return pd.DataFrame()
        d = _at(d, self.at)
        method = self.method if method == "" else method
        if method is not None and "method" in d:
            d = d[d.method == method]
        for col, v in self.where.items():
            if d.empty:
                break
            if v in ("min", "max"):
                d = d[d[col] == getattr(d[col], v)()]
            elif isinstance(v, list):
                d = d[d[col].isin(v)]
            else:
                d = d[d[col] == v]
        return d

    def where_text(self) -> str:
        """``" on pendulum at n_traj 3"``: the selection's one task and its other values (``iteration`` counted from 1)."""
        one = {k: v for k, v in self.where.items() if not isinstance(v, list) and v not in ("min", "max")}
        task = f" on {one.pop('task')}" if "task" in one else ""
        parts = [f"{'iteration' if k == 'iteration' else SHORT.get(k, k)} {v + 1 if k == 'iteration' else v}"
                 for k, v in one.items()]
        return task + (f" at {', '.join(parts)}" if parts else "")


def _at(d: pd.DataFrame, at: str) -> pd.DataFrame:
    if at == "last_iteration" and "iteration" in d:
        return last_iteration(d)
    if at == "sweep" and "iteration" in d:
        return d[d.iteration == d.task.map(final_iteration(d))]
    if at == "loop" and "iteration" in d:
        return pd.concat([loop_t_a(g) for _, g in d.groupby("task")])
    if at == "final_epochs" and "epochs" in d:
        by = [c for c in ("task", "method") if c in d]
        return d[d.epochs == d.groupby(by).epochs.transform("max")] if by else d[d.epochs == d.epochs.max()]
    return d


def groups(rows: pd.DataFrame, per: list[str]) -> dict[tuple, pd.DataFrame]:
    """``{key: rows}`` per value of the ``per`` columns that ``rows`` has (``()``: all rows, one group). A row without
    ``horizon`` (evaluated before T_h was recorded) takes its task's one T_h, if it has one."""
    per = [c for c in per if c in rows]
    if not per:
        return {(): rows} if len(rows) else {}
    if "horizon" in per and "task" in rows:
        one = rows.groupby("task").horizon.transform(lambda h: h.dropna().iloc[0] if h.nunique() == 1 else np.nan)
        rows = rows.assign(horizon=rows.horizon.fillna(one))
    return {(k if isinstance(k, tuple) else (k,)): g for k, g in rows.groupby(per, dropna=False)}


def group_label(key: tuple, per: list[str], rows: pd.DataFrame, every: pd.DataFrame) -> str:
    """``"ur5-rinit (T_h 32, T_a 16)"``: a group's task (with the conversion its chunked rows used) and its other
    ``per`` values, those that differ between ``every``'s groups of that task (Fig. 3's loops; one loop per task
    is named by its task)."""
    per = [c for c in per if c in every]
    if not key:
        return ""
    named = dict(zip(per, key))
    task = named.pop("task", None)
    same = every[every.task == task] if task is not None and "task" in every else every
    varying = [c for c in named if same[c].nunique() > 1 or task is None]
    more = ", ".join(f"{SHORT.get(c, c)} {_num(named[c])}" for c in varying)
    head = f"{task}{conversion_text(rows)}" if task is not None else ""
    return f"{head} ({more})" if head and more else head or more


def _num(v) -> str:
    return f"{v:g}" if isinstance(v, (int, float, np.integer, np.floating)) else str(v)


def estimate_hours(est: pd.DataFrame | None, report: pd.DataFrame | None, key: tuple, per: list[str]) -> float:
    """The hours of a group's runs that have no row in ``report``, from ``est`` (a saved ``sdp pipeline NAME
    --estimate`` table): runs of the group's task and, for Fig. 3's loops, named ``-h<T_h>-ta<T_a>``
    (:func:`sdp_cli.experiments.experiment.group_run_names`); NaN without an estimate."""
    if est is None or est.empty or "total_cpu_h" not in est:
        return float("nan")
    named = dict(zip(per, key))
    mine = est
    if "task" in named:
        mine = mine[mine.task == named["task"]]
    if {"horizon", "t_a"} <= set(named):
        mine = mine[mine.run.str.endswith(f"-h{_num(named['horizon'])}-ta{_num(named['t_a'])}")]
    done = set(report.run) if report is not None and "run" in report else set()
    return float(mine[~mine.run.isin(done)].total_cpu_h.sum())


def paper_ratio(p) -> float:
    """The paper's ratio: a number, or ``[a, b]`` for a / b (the paper's two numbers, quoted as it gives them)."""
    return float(p[0]) / float(p[1]) if isinstance(p, (list, tuple)) else float(p)


#: the TO baselines a column's ``{to}`` expands to: ``(column prefix, name)``; the loop's TO is named by its solver
BASELINES = {"loop": "", "single_shooting": "ss_"}


def baselines(names: list, ctx: dict) -> list[tuple[str, str]]:
    """``[(prefix, name)]`` of the TO baselines ``names`` (``[("", "")]``: none, the columns as they are)."""
    bad = [n for n in names if n not in BASELINES]
    if bad:
        raise SdpError(f"baselines: {bad[0]!r} is not one of {', '.join(BASELINES)}")
    loop = ctx.get("loop_to", "multiple shooting")
    return [(BASELINES[n], loop if n == "loop" else "single shooting") for n in names] or [("", "")]


def has(rows: pd.DataFrame, col: str) -> bool:
    return col in rows and rows[col].notna().any()


def join_words(*xs: str) -> str:
    return " ".join(x for x in xs if x)


def head(group: str, name: str) -> str:
    """``"ur5-rinit (T_h 32, T_a 16), SDP"``; a group without a task after the method: ``"SDP at K 5"``."""
    if not group:
        return name
    return f"{name} at {group}" if group[0].isupper() else f"{group}, {name}"


def missing_text(check, res: dict, keys: list[tuple], methods: list[str]) -> str:
    """``"fig3 not run on ur5-rinit (T_h 32, T_a 31) 17.8 h, ..."``: expected groups with no row of ``methods``."""
    if not keys:
        return ""
    est, report = res.get(f"estimates/{check.experiment}"), check.selection.report(res)
    names = []
    for key in keys:
        named = dict(zip(check.per, key))
        more = ", ".join(f"{SHORT.get(c, c)} {v:g}" if isinstance(v, (int, float)) else f"{c} {v}"
                         for c, v in named.items() if c != "task")
        h = estimate_hours(est, report, key, check.per)
        names.append(join_words(str(named.get("task", "")), f"({more})" if more else "",
                           f"({', '.join(map(method_label, methods))})", f"{h:.1f} h" if np.isfinite(h) and h else ""))
    hours = (f" (hours: the runs not made, `sdp pipeline {check.experiment} --estimate` in one process, "
             f"results/estimates/{check.experiment}.txt)" if est is not None and len(est) else "")
    return f"{check.experiment} not run on " + ", ".join(names) + hours

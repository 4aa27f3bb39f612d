"""Reports that outlive their run folders: ``sdp report --keep-missing``.

A report is written from run folders, but run folders are large and live on the machine that made them
(``/work/sweeps/...``, a cluster's scratch): once they are gone, a report over the runs still there would
drop every other run. With ``--keep-missing`` the report extends the one already in its output folder:

- ``all_runs.csv``: the earlier report's rows of every run that has no evaluation under ``--runs``
  ("carried" runs) are kept as they are, beside the rows read from the run folders (which replace
  the earlier rows of their runs);
- tables drawn from a run's files (``fig2b_<task>.csv``: TO iterations per instance; ``timing_<task>.csv``;
  ``curves/<run>-it<k>.csv``) keep the earlier report's rows of carried runs: by their ``run`` column,
  or, in tables written before they had one, the rows of a method none of whose runs is under ``--runs``
  (exactly the earlier report's rows of that method, since the earlier report had no other runs of it),
  which are then given their run where the method has one carried run in the table;
- ``traj_<task>*.png`` needs the rollouts themselves: it is redrawn only when every method it draws has
  its files here, and otherwise kept from the earlier report (the README says which).

Figures, the ledger and the metrics use the carried rows like any other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from sdp_cli.errors import SdpError
from sdp_cli.report.rows import plain_method, typed_like
from sdp_cli.report.runs import PATH_COLUMNS


@dataclass(frozen=True)
class Carried:
    """The earlier report in ``out`` and the runs taken from it (none: a plain report)."""

    out: Path
    runs: frozenset[str] = frozenset()
    #: per (task, method as drawn): whether some run of it was read from a run folder
    fresh: frozenset[tuple[str, str]] = field(default_factory=frozenset)

    def rows(self, name: str, task: str, drawn: pd.DataFrame) -> pd.DataFrame:
        """The earlier report's ``name`` (a CSV in ``out``) rows that belong to carried runs of ``task`` among
        ``drawn`` (the rows the table draws: ``method``, ``run``): by ``run``, and rows with no run (tables
        written before they had the column) of the methods of those carried runs that have no fresh run.
        Such rows are given their run where one carried run of their method is drawn, so that they stay the
        run's rows once the method has fresh runs too (a second seed at the same budget)."""
        path = self.out / name
        if not self.runs or not path.is_file():
            return pd.DataFrame()
        old = pd.read_csv(path)
        if "method" not in old:
            return pd.DataFrame()
        if "run" not in old:
            old["run"] = None
        drawn = drawn[drawn.run.isin(self.runs)]
        stale = {m for m in set(drawn.method) if (task, m) not in self.fresh}
        # a variant drawn apart now (``sdp-h64-ta63``) was the plain method in a table written while its task
        # had no other variant: the plain name stands for the one stale variant that has it
        variants: dict[str, list[str]] = {}
        for m in sorted(stale):
            variants.setdefault(plain_method(m), []).append(m)
        alias = {p: ms[0] for p, ms in variants.items() if len(ms) == 1 and (task, p) not in self.fresh}
        # only the carried runs the table draws now: a run of another budget (fig2b's SDP at n_traj 16 once
        # 32 ran) is not the table's any more
        rows = old[old.run.isin(set(drawn.run)) | (old.run.isna() & old.method.isin(stale | set(alias)))].copy()
        rows["method"] = rows.method.replace(alias)
        runs = drawn.groupby("method").run
        only = runs.first()[runs.nunique() == 1]
        untagged = rows.run.isna()
        rows["run"] = rows.run.astype(object)      # (a column read with no value at all is not a string column)
        rows.loc[untagged, "run"] = rows.loc[untagged, "method"].map(only).astype(object)
        # each carried run's rows under the name its method is drawn by now (its typed variant)
        rows["method"] = typed_like(rows.run.map(drawn.groupby("run").method.first()).fillna(rows.method), drawn.method)
        return rows

    def keeps_traj(self, rows: pd.DataFrame) -> bool:
        """Whether ``traj_<task>.png`` is kept from the earlier report: among ``rows``, the rows it would draw
        (one task, one budget per method), some method has only carried runs, whose rollouts are gone (a
        method with fresh runs at another budget only is not drawn either)."""
        return bool(self.runs) and any(set(g.run) <= self.runs for _, g in rows.groupby("method"))

    def kept_traj(self, rows: pd.DataFrame, name: str) -> bool:
        """The trajectory figure ``name`` (of ``rows``: one task, one TO family; :func:`~sdp_cli.report.figures.
        traj.traj_parts`) stays the earlier report's: :meth:`keeps_traj` of ``rows``, and the file exists."""
        return self.keeps_traj(rows) and (self.out / name).is_file()


def carry_over(df: pd.DataFrame | None, out: Path, log=lambda s: None) -> tuple[pd.DataFrame, frozenset[str]]:
    """``df`` (rows read from run folders, or None: none) extended by the rows of ``out/all_runs.csv``
    whose runs ``df`` does not have; returns the table and the carried runs."""
    path = out / "all_runs.csv"
    if not path.is_file():
        raise SdpError(f"--keep-missing: no earlier report to keep rows from ({path} not found)")
    try:
        old = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise SdpError(f"corrupt earlier report {path}: {e}") from None
    if "run" not in old or "task" not in old:
        raise SdpError(f"corrupt earlier report {path}: no run/task columns")
    have = set() if df is None else set(df.run)
    kept = old[~old.run.isin(have)]
    runs = frozenset(kept.run.astype(str))
    if runs:
        log(f"keeping {len(kept)} row(s) of {len(runs)} run(s) from {path} (their run folders are not under --runs)")
    # by run (each run's rows in their order): the same table whichever runs are carried
    merged = (kept if df is None else pd.concat([df, kept], ignore_index=True)).sort_values("run", kind="stable")
    # the earlier table's column order, columns it lacks after: a new run adds rows, not a reshuffle
    merged = merged[list(old.columns) + [c for c in merged.columns if c not in old.columns]].reset_index(drop=True)
    for col in (c for c in PATH_COLUMNS if c not in merged):      # carried rows name no files
        merged[col] = None
    if "train_seed" in merged:
        merged["train_seed"] = merged["train_seed"].fillna(0).astype(int)
    if merged.empty:
        raise SdpError(f"nothing to report: no evaluation under --runs and no rows in {path}")
    return merged, runs


def fresh_methods(fdf: pd.DataFrame, carried: frozenset[str]) -> frozenset[tuple[str, str]]:
    """(task, method as drawn) pairs with at least one run read from a run folder."""
    d = fdf[~fdf.run.isin(carried)]
    return frozenset(zip(d.task, d.method))


def carried_lines(df: pd.DataFrame, carried: Carried, kept_traj: list[str],
                  older_runs: frozenset[str] = frozenset()) -> list[str]:
    """README lines: which runs came from the earlier report, which figures were kept from it (``kept_traj``: the
    trajectory figures' file names). ``older_runs``: carried runs not drawn (of an older results version than
    other runs of their task), counted apart; the table lists the drawn ones (``carried.runs``)."""
    if not carried.runs and not older_runs:
        return []
    d = df[df.run.isin(carried.runs)]
    older = (f" ({len(older_runs)} of them of an older results version, kept in all_runs.csv but not drawn)"
             if older_runs else "")
    lines = ["", "## Runs kept from the earlier report (`--keep-missing`)", "",
             f"{len(carried.runs) + len(older_runs)} run(s) have no run folder under --runs{older}; their rows (and "
             "their per-run tables) are the earlier report's, unchanged.", "",
             "| task | method | runs |", "|---|---|---|"]
    for (task, method), g in d.groupby(["task", "method"]):
        lines.append(f"| {task} | {method} | {g.run.nunique()} |")
    if kept_traj:
        lines += ["", "Kept as drawn by the earlier report (some method they draw has no rollouts here): "
                  + ", ".join(f"`{name}`" for name in kept_traj) + "."]
    return lines

"""Saved run-time estimates: ``sdp pipeline NAME --estimate > results/estimates/NAME.txt``, read back.

The reports and the ledger give the hours of runs that were not made from these files (the issue's "mark the
rest 'not run' with their --estimate hours"), instead of re-calibrating (which trains for a minute and moves
with the machine's load). The table is the one :func:`sdp_cli.experiments.estimate.format_estimate` prints.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

#: the columns of the printed table that are not numbers
TEXT_COLUMNS = ("run", "task", "method")


def read_estimate(path: Path) -> pd.DataFrame:
    """The per-run table of a saved estimate: one row per run, the printed columns (``run``, ``task``,
    ``method``, ``iterations``, ``steps``, ``samples``, ``train_cpu_h``, ..., ``total_cpu_h``). Lines before the
    table (the time and load it was made at, the calibrations) and the totals after it are skipped. Empty
    when the file is missing or holds no table."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError:
        return pd.DataFrame()
    head = next((i for i, ln in enumerate(lines) if ln.split()[:1] == ["run"]), None)
    if head is None:
        return pd.DataFrame()
    cols = lines[head].split()
    rows = []
    for ln in lines[head + 1:]:
        vals = ln.split()
        if len(vals) != len(cols):
            break
        rows.append(vals)
    df = pd.DataFrame(rows, columns=cols)
    for c in cols:
        if c not in TEXT_COLUMNS:
            df[c] = pd.to_numeric(df[c], errors="coerce")
    return df


def estimated_hours(path: Path) -> dict[str, float]:
    """``{run: hours}`` of a saved estimate: every stage of the run in one process on the CPU
    (``total_cpu_h``); empty without a file or that column."""
    df = read_estimate(path)
    if df.empty or "total_cpu_h" not in df:
        return {}
    return dict(zip(df.run, df.total_cpu_h.astype(float)))

"""The results version (:data:`sdp_cli.RESULTS_VERSION`) of each report row: what its run measured.

Loops record it since version 4 (``loop_config.json``, then each evaluation's row). A row without it (a run
made before) gets the version of the code that computed it: the ``RESULTS_VERSION`` literal of
``sdp_cli/__init__.py`` at the row's code revision (``git_rev``), read from this repository's git history; a
revision older than the constant is version 1, one git does not know (a shallow clone, another repository,
``unknown``) stays unknown (NaN). A row computed by two revisions (``rollouts+refinement``) has the older
version of the two.
"""

from __future__ import annotations

import functools
import math
import re
import subprocess
from pathlib import Path

import pandas as pd

_ROOT = Path(__file__).resolve().parents[2]
_LITERAL = re.compile(r"^RESULTS_VERSION\s*=\s*(\d+)\s*$", re.M)
_SHA = re.compile(r"[0-9a-f]{7,40}")


@functools.cache
def version_at(rev: str, root: Path = _ROOT) -> float:
    """The results version of the code at commit ``rev`` of the repository at ``root``: the integer
    ``RESULTS_VERSION`` of its ``sdp_cli/__init__.py``, 1 where that file has no such constant yet, NaN where git
    cannot show it or the constant is not an integer literal."""
    if not _SHA.fullmatch(rev):
        return math.nan
    try:
        out = subprocess.run(["git", "show", f"{rev}:sdp_cli/__init__.py"], cwd=root, capture_output=True,
                             text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return math.nan
    if out.returncode != 0:
        return math.nan
    if m := _LITERAL.search(out.stdout):
        return float(m.group(1))
    return math.nan if "RESULTS_VERSION" in out.stdout else 1.0


def revision_version(git_rev, root: Path = _ROOT) -> float:
    """:func:`version_at` of a row's ``git_rev`` (``sha``, ``sha+dirty``, ``sha+sha`` for rollouts and a
    refinement made by different code): the oldest of its commits, NaN if any is unknown."""
    parts = [p for p in str(git_rev).split("+") if p and p != "dirty"]
    versions = [version_at(p, root) for p in parts]
    return math.nan if not versions or any(math.isnan(v) for v in versions) else min(versions)


def with_results_version(df: pd.DataFrame, root: Path = _ROOT) -> pd.DataFrame:
    """``df`` with ``results_version`` on every row: as recorded, else from the row's code revision (in the
    repository at ``root``)."""
    if df.empty or "git_rev" not in df:
        return df
    have = df["results_version"] if "results_version" in df else pd.Series(math.nan, index=df.index)
    have = pd.to_numeric(have, errors="coerce")
    missing = have.isna()
    if missing.any():
        have = have.where(~missing, df["git_rev"].map(lambda r: revision_version(r, root)))
    return df.assign(results_version=have)


def version_text(versions) -> str:
    """``"1"``, ``"1, 4"`` or ``"unknown"`` (some rows' version unknown) of a column of versions."""
    s = pd.Series(list(versions), dtype=float)
    known = sorted({int(v) for v in s.dropna()})
    return ", ".join(map(str, known)) + (", unknown" if s.isna().any() and known else
                                         "unknown" if s.isna().any() else "")

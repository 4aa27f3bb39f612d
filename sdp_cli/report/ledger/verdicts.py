"""The generic rules every claim is judged by, parameterised by results/claims.yaml: a :class:`Row` per claim,
numbers as ``mean ± ci (n seeds)`` (:func:`fmt`), ratio claims by :func:`ratio_verdict`, claims made of several
checks by :func:`all_any` and :func:`combine`. The thresholds (``solved``, ``within``, a ratio's ``keep`` and
``partly`` shares) come from the yaml's ``rules`` and each claim's ``params``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from sdp_cli.report.rows import mean_ci, per_seed

VERDICTS = ("reproduced", "partly", "not reproduced", "not run")


@dataclass
class Row:
    ours: str
    verdict: str
    detail: str = ""     # what was measured beyond the headline number (shown in the notes column)
    rule: str = ""       # the claim's checks in words (shown once in the notes column)


def fmt(values, digits: int = 3, pct: bool = False, unit: str = "") -> str:
    """``mean ± ci (n seeds)`` of per-seed values."""
    m, h, n = mean_ci(pd.Series(values, dtype=float))
    if not np.isfinite(m):
        return "diverged" if np.isinf(m) else "n/a"
    f = (lambda v: f"{100 * v:.0f}%") if pct else (lambda v: f"{v:.{digits}g}{unit}")
    ci = f" ± {f(h)}" if np.isfinite(h) else ""
    return f"{f(m)}{ci} ({n} seed{'s' if n != 1 else ''})"


def distance_text(rows: pd.DataFrame) -> str:
    """``", final distance 0.12 ± 0.03 m (5 seeds)"``: the per-seed median distance to the goal at the final
    step (``goal_distance_median``) of ``rows``, beside a claim's cost and success; ``""`` where the rows lack it."""
    if "goal_distance_median" not in rows or not rows.goal_distance_median.notna().any():
        return ""
    return ", final distance " + fmt(per_seed(rows, "goal_distance_median")).replace(" (", " m (", 1)


def pct_text(share: float) -> str:
    """``0.1`` -> ``"10%"``."""
    return f"{100 * share:g}%"


def ratio_verdict(r: float, paper: float, keep: float, partly: float) -> str:
    """A ratio claim ``paper`` (> 1): reproduced when ours keeps at least ``keep`` of the paper's effect
    (``r - 1 >= keep (paper - 1)``), partly with at least ``partly`` of it, else not reproduced."""
    if not np.isfinite(r):
        return "not reproduced"
    if r - 1 >= keep * (paper - 1):
        return "reproduced"
    return "partly" if r - 1 >= partly * (paper - 1) else "not reproduced"


def all_any(ok: list[bool], complete: bool = True) -> str:
    """Several checks of one claim: reproduced when there are some, all hold and the evidence is
    ``complete``; partly when some hold; else not reproduced."""
    if ok and all(ok) and complete:
        return "reproduced"
    return "partly" if any(ok) else "not reproduced"


def combine(verdicts: list[str]) -> str:
    """One verdict from several parts: reproduced if all are, not reproduced if all are not, else partly."""
    if verdicts and all(v == "reproduced" for v in verdicts):
        return "reproduced"
    return "not reproduced" if all(v == "not reproduced" for v in verdicts) else "partly"

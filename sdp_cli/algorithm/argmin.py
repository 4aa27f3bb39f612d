"""ArgminCost (Algorithm 1, line 8): which of the solves of one instance is kept, and what that says.

:func:`argmin_cost` keeps the cheapest converged solve (the policy guess's on a tie); its codes are stored
per instance in ``inst_winner``. :func:`policy_outcomes` counts, over those codes, the instances where the
policy guess really beat TO alone and those where both reached one optimum. NumPy only: the evaluation
and the report read it without the solvers.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: winner codes stored in ``inst_winner``
WIN_NONE, WIN_POLICY, WIN_BASELINE = -1, 0, 1
#: relative cost difference under which two converged solves tie in ArgminCost
TIE_RTOL = 1e-9


def tie_tolerance(cost):
    """The cost difference within which a solve ties with one of cost ``cost`` (scalar or array)."""
    return TIE_RTOL * np.maximum(1.0, np.abs(cost))


def argmin_cost(candidates: Sequence) -> int | None:
    """Index of the converged candidate with the lowest cost; None if none converged.

    ``candidates`` are objects with ``converged`` and ``cost`` (e.g. ``SolveResult``);
    ``None`` entries (candidates that were not computed) are skipped. Costs within
    ``TIE_RTOL`` of each other are a tie, won by the earlier candidate (the policy guess):
    two solves that reach the same optimum differ by rounding (1e-13), which must not decide.
    """
    best, best_cost = None, np.inf
    for i, c in enumerate(candidates):
        if c is None or not bool(c.converged) or not np.isfinite(c.cost):
            continue
        if c.cost < best_cost - (tie_tolerance(best_cost) if np.isfinite(best_cost) else TIE_RTOL):
            best, best_cost = i, float(c.cost)
    return best


def policy_outcomes(winner, pol_cost, base_cost, base_converged) -> tuple[int, int]:
    """``(wins, ties)`` of the policy guess over per-instance arrays ``(N,)``: a win is an instance
    ArgminCost kept from the policy guess where TO alone failed (or was not run) or ended more than
    ``TIE_RTOL`` dearer; a tie, one where both reached the same cost (ArgminCost keeps the policy's,
    which says nothing about the policy)."""
    winner, pol_cost, base_cost = (np.asarray(a) for a in (winner, pol_cost, base_cost))
    kept = winner == WIN_POLICY
    base_ok = np.asarray(base_converged).astype(bool) & np.isfinite(base_cost)
    with np.errstate(invalid="ignore"):
        tie = base_ok & (np.abs(base_cost - pol_cost) <= tie_tolerance(pol_cost))
    return int(np.sum(kept & ~tie)), int(np.sum(kept & tie))

"""The augmented-Lagrangian outer loop of box-FDDP for state constraints ``h(x_t) <= 0`` on ``x_1..x_T``
(the quadrotor's floor, ceiling and columns), as ProxDDP and ALTRO handle them: the DDP minimizes the cost
plus the Powell-Hestenes-Rockafellar penalty

    ``psi(h; lam, rho) = 1/(2 rho) sum_i (max(0, lam_i + rho h_i)^2 - lam_i^2)``

per constrained state, with gradient ``mu' dh`` (``mu = max(0, lam + rho h)``, the multiplier estimate) and the
Gauss-Newton Hessian ``rho dh_A' dh_A`` over the constraints with ``lam + rho h > 0``. Outer updates (ours,
decided before any run, the textbook rule of Nocedal & Wright, Alg. 17.4, and Bertsekas): when an instance's
inner DDP is stationary to ``inner_tol``, ``lam <- mu``; if the largest violation did not fall below
``VIOL_DECREASE`` x the one at the previous update, ``rho <- RHO_FACTOR rho`` (at most ``RHO_MAX``); the next
inner tolerance is ``INNER_FACTOR`` x the last (not below the solve's ``tol``). An update that would change nothing
(no violation, the multipliers already ``mu``) tightens the inner tolerance and the iteration steps as usual
(it used to cost an iteration without a step). Converged: stationary to ``tol`` with every ``h <= H_TOL`` (the
same 1e-6 as fatrop's constraint tolerance).
"""

from __future__ import annotations

import numpy as np

RHO_INIT, RHO_FACTOR, RHO_MAX = 10.0, 10.0, 1e8
VIOL_DECREASE = 0.25
INNER_TOL_INIT, INNER_FACTOR = 1e-3, 0.1
H_TOL = 1e-6


def multipliers(h: np.ndarray, lam: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """``mu = max(0, lam + rho h)``: ``h, lam (n, T, n_h)``, ``rho (n,)``."""
    return np.maximum(0.0, lam + rho[:, None, None] * h)


def penalty(h: np.ndarray, lam: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """``sum_t psi(h_t; lam_t, rho)`` per instance ``(n,)``."""
    mu = multipliers(h, lam, rho)
    return np.sum(mu ** 2 - lam ** 2, axis=(1, 2)) / (2 * rho)


def derivatives(h: np.ndarray, dh: np.ndarray, lam: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient ``(n, T, ndx)`` and Gauss-Newton Hessian ``(n, T, ndx, ndx)`` of the penalty; ``dh (n, T, n_h,
    ndx)`` the constraint Jacobians in the tangent space."""
    mu = multipliers(h, lam, rho)
    act = (lam + rho[:, None, None] * h > 0).astype(float)
    grad = np.einsum("ntk,ntkd->ntd", mu, dh)
    hess = rho[:, None, None, None] * np.einsum("ntk,ntkd,ntke->ntde", act, dh, dh)
    return grad, hess


def violation(h: np.ndarray) -> np.ndarray:
    """Largest constraint violation ``max(0, h)`` per instance ``(n,)``."""
    return np.maximum(h, 0.0).max(axis=(1, 2), initial=0.0)

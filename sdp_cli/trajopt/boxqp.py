"""Box-constrained QP by projected Newton (Tassa, Mansard, Todorov, "Control-limited differential dynamic
programming", ICRA 2014, Algorithm 3), the backward-pass step of box-FDDP (:mod:`sdp_cli.trajopt.ddp`), compiled
with numba (one problem at a time: :func:`box_qp_one`, called by the compiled backward pass of
:mod:`sdp_cli.trajopt.ddp_kernels`; :func:`box_qp` for a batch).

``min_x 1/2 x^T H x + g^T x  s.t.  lo <= x <= hi``, ``H (m, m)`` symmetric positive definite. Each iteration: the
gradient, the clamped set (at a bound with the gradient pushing outward), a Newton step on the free set with the
clamped coordinates fixed (Cholesky), and an Armijo line search along the projected arc.
"""

from __future__ import annotations

import numpy as np
from numba import njit

MAX_ITER = 100
MIN_GRAD = 1e-10        # stop when the free gradient's norm is below this (relative to 1 + |g|)
MIN_STEP = 1e-22        # line search gives up below this step
ARMIJO = 0.1
STEP_DEC = 0.6


@njit(cache=True)
def cholesky(M, L):
    """``L`` lower triangular with ``L L' = M`` (``M`` symmetric); False where ``M`` is not positive definite."""
    m = M.shape[0]
    for j in range(m):
        s = M[j, j]
        for p in range(j):
            s -= L[j, p] * L[j, p]
        if not s > 0.0:
            return False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, m):
            s = M[i, j]
            for p in range(j):
                s -= L[i, p] * L[j, p]
            L[i, j] = s / L[j, j]
        for i in range(j):
            L[i, j] = 0.0
    return True


@njit(cache=True)
def chol_solve(L, b):
    """``(L L')^-1 b`` in place, ``b (m, k)``."""
    m, k = b.shape
    for c in range(k):
        for i in range(m):
            s = b[i, c]
            for p in range(i):
                s -= L[i, p] * b[p, c]
            b[i, c] = s / L[i, i]
        for i in range(m - 1, -1, -1):
            s = b[i, c]
            for p in range(i + 1, m):
                s -= L[p, i] * b[p, c]
            b[i, c] = s / L[i, i]


@njit(cache=True)
def free_solve(H, rhs, free, out):
    """``out`` with ``H_ff out_f = rhs_f`` and ``out_c = 0`` on the clamped rows (``H`` positive definite)."""
    m, k = rhs.shape
    Hm = np.eye(m)
    for i in range(m):
        for j in range(m):
            if free[i] and free[j]:
                Hm[i, j] = H[i, j]
    L = np.zeros((m, m))
    cholesky(Hm, L)
    for i in range(m):
        for c in range(k):
            out[i, c] = rhs[i, c] if free[i] else 0.0
    chol_solve(L, out)


@njit(cache=True)
def _qp_value(H, g, x):
    m = len(x)
    v = 0.0
    for i in range(m):
        s = 0.0
        for j in range(m):
            s += H[i, j] * x[j]
        v += 0.5 * x[i] * s + g[i] * x[i]
    return v


@njit(cache=True)
def box_qp_one(H, g, lo, hi, x, free):
    """Projected Newton on ``min 1/2 x'Hx + g'x, lo <= x <= hi`` from ``x`` (clipped), in place; ``free``: the
    coordinates not clamped at the solution. Returns whether it converged (:func:`sdp_cli.trajopt.boxqp.box_qp`)."""
    m = len(g)
    scale = 1.0
    for i in range(m):
        x[i] = min(max(x[i], lo[i]), hi[i])
        scale = max(scale, 1.0 + abs(g[i]))
    grad, dx, cand = np.empty(m), np.empty((m, 1)), np.empty(m)
    for _ in range(MAX_ITER):
        norm = 0.0
        for i in range(m):
            s = g[i]
            for j in range(m):
                s += H[i, j] * x[j]
            grad[i] = s
            free[i] = not ((x[i] <= lo[i] and s > 0.0) or (x[i] >= hi[i] and s < 0.0))
            if free[i]:
                norm += s * s
        if np.sqrt(norm) <= MIN_GRAD * scale:
            return True
        free_solve(H, grad.reshape(m, 1), free, dx)
        f0 = _qp_value(H, g, x)
        step = 1.0
        while True:
            lin = 0.0
            for i in range(m):
                cand[i] = min(max(x[i] - step * dx[i, 0], lo[i]), hi[i])
                lin += grad[i] * (cand[i] - x[i])
            if _qp_value(H, g, cand) <= f0 + ARMIJO * lin:
                x[:] = cand
                break
            step *= STEP_DEC
            if step < MIN_STEP:          # no decrease possible: converged to the precision we have
                return True
    return False


@njit(cache=True)
def _box_qp_batch(H, g, lo, hi, x, free, ok):
    for i in range(len(g)):
        ok[i] = box_qp_one(H[i], g[i], lo[i], hi[i], x[i], free[i])


def box_qp(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None = None):
    """A batch: ``H (n, m, m)``, ``g, lo, hi, x0 (n, m)``. Returns ``(x (n, m), free (n, m) bool, ok (n,) bool)``:
    the minimizers, the free (not clamped) coordinates at the solution, and whether each problem converged
    (``MAX_ITER`` projected Newton iterations)."""
    g = np.ascontiguousarray(g, dtype=float)
    n, m = g.shape
    x = np.zeros((n, m)) if x0 is None else np.array(x0, dtype=float)
    free, ok = np.ones((n, m), dtype=bool), np.zeros(n, dtype=bool)
    _box_qp_batch(np.ascontiguousarray(H, dtype=float), g, np.ascontiguousarray(lo, dtype=float),
                  np.ascontiguousarray(hi, dtype=float), x, free, ok)
    return x, free, ok

"""Batched box-constrained QP by projected Newton (Tassa, Mansard, Todorov, "Control-limited differential
dynamic programming", ICRA 2014, Algorithm 3), the backward-pass step of box-FDDP (:mod:`sdp_cli.trajopt.ddp`).

``min_x 1/2 x^T H x + g^T x  s.t.  lo <= x <= hi``, for a batch of ``n`` problems of size ``m`` at once:
``H (n, m, m)`` symmetric positive definite, ``g, lo, hi, x0 (n, m)``. Each iteration: the gradient, the
clamped set (at a bound with the gradient pushing outward), a Newton step on the free set with the clamped
coordinates fixed, and an Armijo line search along the projected arc. Every operation is an array
operation over the batch; finished problems stop changing.
"""

from __future__ import annotations

import numpy as np

MAX_ITER = 100
MIN_GRAD = 1e-10        # stop when the free gradient's norm is below this (relative to 1 + |g|)
MIN_STEP = 1e-22        # line search gives up below this step
ARMIJO = 0.1
STEP_DEC = 0.6


def _value(H, g, x):
    return 0.5 * np.einsum("ni,nij,nj->n", x, H, x) + np.einsum("ni,ni->n", g, x)


def free_solve(H: np.ndarray, rhs: np.ndarray, free: np.ndarray) -> np.ndarray:
    """``X`` with ``H_ff X_f = rhs_f`` and ``X_c = 0`` on the clamped rows: ``H (n, m, m)``, ``rhs (n, m, k)``,
    ``free (n, m)`` bool (the clamped rows and columns of ``H`` are replaced by the identity)."""
    ff = free[:, :, None] & free[:, None, :]
    Hm = np.where(ff, H, 0.0) + np.eye(H.shape[-1]) * (~free)[:, :, None]
    return np.linalg.solve(Hm, np.where(free[:, :, None], rhs, 0.0))


def box_qp(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None = None):
    """``(x (n, m), free (n, m) bool, ok (n,) bool)``: the minimizers, the free (not clamped) coordinates at
    the solution, and whether each problem converged (``MAX_ITER`` projected Newton iterations)."""
    n, m = g.shape
    x = np.clip(np.zeros((n, m)) if x0 is None else x0, lo, hi)
    done = np.zeros(n, dtype=bool)
    free = np.ones((n, m), dtype=bool)
    scale = 1.0 + np.abs(g).max(axis=1)
    for _ in range(MAX_ITER):
        act = ~done
        if not act.any():
            break
        Ha, ga, xa, la, ha = H[act], g[act], x[act], lo[act], hi[act]
        grad = ga + np.einsum("nij,nj->ni", Ha, xa)
        clamped = ((xa <= la) & (grad > 0)) | ((xa >= ha) & (grad < 0))
        fr = ~clamped
        conv = np.linalg.norm(np.where(fr, grad, 0.0), axis=1) <= MIN_GRAD * scale[act]
        idx = np.flatnonzero(act)
        free[idx] = fr
        done[idx[conv]] = True
        if conv.all():
            break
        keep = ~conv
        idx, Ha, ga, xa, la, ha, grad, fr = idx[keep], Ha[keep], ga[keep], xa[keep], la[keep], ha[keep], grad[keep], fr[keep]
        dx = -free_solve(Ha, grad[:, :, None], fr)[:, :, 0]
        f0 = _value(Ha, ga, xa)
        step = np.ones(len(idx))
        searching = np.ones(len(idx), dtype=bool)
        xn = xa.copy()
        while searching.any():
            s = step[searching, None]
            cand = np.clip(xa[searching] + s * dx[searching], la[searching], ha[searching])
            fc = _value(Ha[searching], ga[searching], cand)
            ok = fc <= f0[searching] + ARMIJO * np.einsum("ni,ni->n", grad[searching], cand - xa[searching])
            sidx = np.flatnonzero(searching)
            xn[sidx[ok]] = cand[ok]
            searching[sidx[ok]] = False
            step[searching] *= STEP_DEC
            tiny = searching & (step < MIN_STEP)
            searching[tiny] = False            # no decrease possible: converged to the precision we have
            done[idx[tiny]] = True
        x[idx] = xn
    return x, free, done

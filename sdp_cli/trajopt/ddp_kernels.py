"""Box-FDDP's backward pass compiled (numba): the Riccati recursion with gaps and the projected-Newton box QP,
one instance at a time in machine code (:func:`backward`).

The recursion is sequential in t and its matrices are small (``nx <= 12``, ``nu <= 6``): as numpy array operations
over the batch it cost ~25 calls of a few microseconds each per step, whatever the batch (77% of a double-pendulum
solve, 59% of UR5's: docs/benchmarks.md). The algorithm is that of :mod:`sdp_cli.trajopt.ddp` (the backward pass)
and :mod:`sdp_cli.trajopt.boxqp` (Tassa et al. 2014, Algorithm 3), with its constants; ``tests/test_ddp_kernels.py``
checks it against the array version on random problems. Factorizations are Cholesky (the matrices are symmetric
positive definite where they are used); a ``Quu + reg I`` that is not is reported (``ok`` False) and the instance's
recursion goes on with the identity, as the array version's, its outputs unused by the solver.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sdp_cli.trajopt.boxqp import box_qp_one, cholesky, chol_solve, free_solve


@njit(cache=True)
def backward(A, B, lx, lu, lxx, luu, lux, lTx, lTxx, gaps, U, u_lb, u_ub, reg):
    """The backward pass of every instance: ``A (n,T,nx,nx)``, ``B (n,T,nx,nu)``, ``lx (n,T,nx)``, ``lu (n,T,nu)``,
    ``lxx (n,T,nx,nx)``, ``luu (n,T,nu,nu)``, ``lux (n,T,nu,nx)``, ``lTx (n,nx)``, ``lTxx (n,nx,nx)``, ``gaps
    (n,T+1,nx)``, ``U (n,T,nu)``, bounds ``(nu,)``, ``reg (n,)``. Returns ``(k (n,T,nu), K (n,T,nu,nx), Vx
    (n,T+1,nx), free (n,T,nu), stop (n,), ok (n,))`` as :meth:`sdp_cli.trajopt.ddp_passes.PassesMixin._backward`."""
    n, T, nx, nu = B.shape[0], B.shape[1], B.shape[2], B.shape[3]
    k, K = np.zeros((n, T, nu)), np.zeros((n, T, nu, nx))
    Vx_all = np.zeros((n, T + 1, nx))
    free_all = np.ones((n, T, nu), dtype=np.bool_)
    stop = np.zeros(n)
    ok = np.ones(n, dtype=np.bool_)
    Vx, Vxx, Vxp = np.empty(nx), np.empty((nx, nx)), np.empty(nx)
    Qx, Qu = np.empty(nx), np.empty(nu)
    VA, VB = np.empty((nx, nx)), np.empty((nx, nu))
    Qxx, Quu, Qux, Quu_r = np.empty((nx, nx)), np.empty((nu, nu)), np.empty((nu, nx)), np.empty((nu, nu))
    L = np.zeros((nu, nu))
    sol = np.empty((nu, 1 + nx))
    lo, hi, kt, fr = np.empty(nu), np.empty(nu), np.empty(nu), np.empty(nu, dtype=np.bool_)
    Kt, QK = np.empty((nu, nx)), np.empty((nu, nx))
    w = np.empty(nu)
    eye = np.eye(nu)
    for i in range(n):
        Vx[:] = lTx[i]
        Vxx[:, :] = lTxx[i]
        Vx_all[i, T] = Vx
        for t in range(T - 1, -1, -1):
            a, b = A[i, t], B[i, t]
            for r in range(nx):
                s = Vx[r]
                for c in range(nx):
                    s += Vxx[r, c] * gaps[i, t + 1, c]
                Vxp[r] = s
            for r in range(nx):
                s = lx[i, t, r]
                for c in range(nx):
                    s += a[c, r] * Vxp[c]
                Qx[r] = s
            for r in range(nu):
                s = lu[i, t, r]
                for c in range(nx):
                    s += b[c, r] * Vxp[c]
                Qu[r] = s
            for r in range(nx):
                for c in range(nx):
                    s = 0.0
                    for p in range(nx):
                        s += Vxx[r, p] * a[p, c]
                    VA[r, c] = s
                for c in range(nu):
                    s = 0.0
                    for p in range(nx):
                        s += Vxx[r, p] * b[p, c]
                    VB[r, c] = s
            for r in range(nx):
                for c in range(nx):
                    s = lxx[i, t, r, c]
                    for p in range(nx):
                        s += a[p, r] * VA[p, c]
                    Qxx[r, c] = s
            for r in range(nu):
                for c in range(nu):
                    s = luu[i, t, r, c]
                    for p in range(nx):
                        s += b[p, r] * VB[p, c]
                    Quu[r, c] = s
                for c in range(nx):
                    s = lux[i, t, r, c]
                    for p in range(nx):
                        s += b[p, r] * VA[p, c]
                    Qux[r, c] = s
            for r in range(nu):
                for c in range(nu):
                    Quu_r[r, c] = 0.5 * (Quu[r, c] + Quu[c, r]) + (reg[i] if r == c else 0.0)
            if not cholesky(Quu_r, L):
                ok[i] = False                    # this instance retries with more reg
                Quu_r[:, :] = eye
                cholesky(Quu_r, L)
            out = False
            for r in range(nu):
                lo[r], hi[r] = u_lb[r] - U[i, t, r], u_ub[r] - U[i, t, r]
                sol[r, 0] = -Qu[r]
                for c in range(nx):
                    sol[r, 1 + c] = -Qux[r, c]
            chol_solve(L, sol)                  # unconstrained step and gain
            for r in range(nu):
                kt[r] = sol[r, 0]
                fr[r] = True
                for c in range(nx):
                    Kt[r, c] = sol[r, 1 + c]
                out = out or kt[r] < lo[r] or kt[r] > hi[r]
            if out:
                box_qp_one(Quu_r, Qu, lo, hi, kt, fr)
                free_solve(Quu_r, Qux, fr, Kt)
                for r in range(nu):
                    for c in range(nx):
                        Kt[r, c] = -Kt[r, c]
            for r in range(nu):
                k[i, t, r] = kt[r]
                free_all[i, t, r] = fr[r]
                for c in range(nx):
                    K[i, t, r, c] = Kt[r, c]
                if fr[r]:
                    stop[i] += Qu[r] * Qu[r]
            # V_x = Q_x + K'(Quu k + Qu) + Qux' k;  V_xx = Qxx + K'Quu K + K'Qux + Qux'K (symmetrized)
            for r in range(nu):
                s = Qu[r]
                for c in range(nu):
                    s += Quu[r, c] * kt[c]
                w[r] = s
            for r in range(nx):
                s = Qx[r]
                for p in range(nu):
                    s += Kt[p, r] * w[p] + Qux[p, r] * kt[p]
                Vx[r] = s
            for r in range(nu):
                for c in range(nx):
                    s = 0.0
                    for p in range(nu):
                        s += Quu[r, p] * Kt[p, c]
                    QK[r, c] = s
            for r in range(nx):
                for c in range(nx):
                    s = Qxx[r, c]
                    for p in range(nu):
                        s += Kt[p, r] * (QK[p, c] + Qux[p, c]) + Qux[p, r] * Kt[p, c]
                    Qxx[r, c] = s
            for r in range(nx):
                for c in range(nx):
                    Vxx[r, c] = 0.5 * (Qxx[r, c] + Qxx[c, r])
            Vx_all[i, t] = Vx
    return k, K, Vx_all, free_all, stop, ok


@njit(cache=True)
def lq_model(A, B, lx, lu, lxx, luu, lux, lTx, lTxx, gaps, k, K):
    """``(d1 (n,), d2 (n,))``: gradient and curvature of the LQ model along the full step ``du = k + K dx`` with the
    gaps (``dx_{t+1} = A dx + B du + gap_{t+1}``, ``dx_0 = gap_0``), as
    :meth:`sdp_cli.trajopt.ddp_passes.PassesMixin._model`."""
    n, T, nx, nu = B.shape[0], B.shape[1], B.shape[2], B.shape[3]
    d1, d2 = np.zeros(n), np.zeros(n)
    dx, du, nxt = np.empty(nx), np.empty(nu), np.empty(nx)
    for i in range(n):
        dx[:] = gaps[i, 0]
        a1, a2 = 0.0, 0.0
        for t in range(T):
            for r in range(nu):
                s = k[i, t, r]
                for c in range(nx):
                    s += K[i, t, r, c] * dx[c]
                du[r] = s
            for r in range(nx):
                a1 += lx[i, t, r] * dx[r]
                s = 0.0
                for c in range(nx):
                    s += lxx[i, t, r, c] * dx[c]
                a2 += dx[r] * s
            for r in range(nu):
                a1 += lu[i, t, r] * du[r]
                s, q = 0.0, 0.0
                for c in range(nx):
                    s += lux[i, t, r, c] * dx[c]
                for c in range(nu):
                    q += luu[i, t, r, c] * du[c]
                a2 += du[r] * (2.0 * s + q)
            for r in range(nx):
                s = gaps[i, t + 1, r]
                for c in range(nx):
                    s += A[i, t, r, c] * dx[c]
                for c in range(nu):
                    s += B[i, t, r, c] * du[c]
                nxt[r] = s
            dx[:] = nxt
        for r in range(nx):
            a1 += lTx[i, r] * dx[r]
            s = 0.0
            for c in range(nx):
                s += lTxx[i, r, c] * dx[c]
            a2 += dx[r] * s
        d1[i], d2[i] = a1, a2
    return d1, d2

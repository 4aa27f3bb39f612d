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
def _mm(A, B, out):
    """``out = A B``."""
    for r in range(A.shape[0]):
        for c in range(B.shape[1]):
            s = 0.0
            for p in range(A.shape[1]):
                s += A[r, p] * B[p, c]
            out[r, c] = s


@njit(cache=True)
def _ab(C, A, B, out):
    """``out = C + A B`` (``out`` may be ``C``; ``A`` may be a transposed view: ``C + A' B``)."""
    for r in range(A.shape[0]):
        for c in range(B.shape[1]):
            s = C[r, c]
            for p in range(A.shape[1]):
                s += A[r, p] * B[p, c]
            out[r, c] = s


@njit(cache=True)
def _av(c, A, v, out):
    """``out = c + A v`` (``out`` may be ``c``; ``A`` may be a transposed view: ``c + A' v``)."""
    for r in range(A.shape[0]):
        s = c[r]
        for p in range(A.shape[1]):
            s += A[r, p] * v[p]
        out[r] = s


@njit(cache=True)
def _dot(v, w):
    """``v' w`` (numba's ``np.dot`` needs SciPy's BLAS)."""
    s = 0.0
    for r in range(len(v)):
        s += v[r] * w[r]
    return s


@njit(cache=True)
def _quad(v, M, w):
    """``v' M w``."""
    s = 0.0
    for r in range(M.shape[0]):
        for c in range(M.shape[1]):
            s += v[r] * M[r, c] * w[c]
    return s


@njit(cache=True)
def backward(A, B, lx, lu, lxx, luu, lux, lTx, lTxx, gaps, U, u_lb, u_ub, reg):
    """The backward pass of every instance: ``A (n,T,nx,nx)``, ``B (n,T,nx,nu)``, ``lx (n,T,nx)``, ``lu (n,T,nu)``,
    ``lxx (n,T,nx,nx)``, ``luu (n,T,nu,nu)``, ``lux (n,T,nu,nx)``, ``lTx (n,nx)``, ``lTxx (n,nx,nx)``, ``gaps
    (n,T+1,nx)``, ``U (n,T,nu)``, bounds ``(nu,)``, ``reg (n,)``. Returns ``(k (n,T,nu), K (n,T,nu,nx), Vx
    (n,T+1,nx), free (n,T,nu), stop (n,), ok (n,))`` as the array version's (tests/test_ddp_kernels.py)."""
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
    lo, hi, fr = np.empty(nu), np.empty(nu), np.empty(nu, dtype=np.bool_)
    Kt, QK = np.empty((nu, nx)), np.empty((nu, nx))
    w = np.empty(nu)
    eye = np.eye(nu)
    for i in range(n):
        Vx[:] = lTx[i]
        Vxx[:, :] = lTxx[i]
        Vx_all[i, T] = Vx
        for t in range(T - 1, -1, -1):
            a, b = A[i, t], B[i, t]
            _av(Vx, Vxx, gaps[i, t + 1], Vxp)               # V'_x = V_x + V_xx fbar
            _av(lx[i, t], a.T, Vxp, Qx)
            _av(lu[i, t], b.T, Vxp, Qu)
            _mm(Vxx, a, VA)
            _mm(Vxx, b, VB)
            _ab(lxx[i, t], a.T, VA, Qxx)
            _ab(luu[i, t], b.T, VB, Quu)
            _ab(lux[i, t], b.T, VA, Qux)
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
                sol[r, 1:] = -Qux[r]
            chol_solve(L, sol)                   # unconstrained step and gain
            kt = k[i, t]
            kt[:] = sol[:, 0]
            Kt[:, :] = sol[:, 1:]
            fr[:] = True
            for r in range(nu):
                out = out or kt[r] < lo[r] or kt[r] > hi[r]
            if out:
                box_qp_one(Quu_r, Qu, lo, hi, kt, fr)
                free_solve(Quu_r, Qux, fr, Kt)
                Kt *= -1.0
            K[i, t] = Kt
            free_all[i, t] = fr
            for r in range(nu):
                if fr[r]:
                    stop[i] += Qu[r] * Qu[r]
            # V_x = Q_x + K'(Quu k + Qu) + Qux' k;  V_xx = Qxx + K'(Quu K + Qux) + Qux' K, symmetrized
            _av(Qu, Quu, kt, w)
            _av(Qx, Kt.T, w, Vx)
            _av(Vx, Qux.T, kt, Vx)
            _mm(Quu, Kt, QK)
            QK += Qux
            _ab(Qxx, Kt.T, QK, Qxx)
            _ab(Qxx, Qux.T, Kt, Qxx)
            for r in range(nx):
                for c in range(nx):
                    Vxx[r, c] = 0.5 * (Qxx[r, c] + Qxx[c, r])
            Vx_all[i, t] = Vx
    return k, K, Vx_all, free_all, stop, ok


@njit(cache=True)
def lq_model(A, B, lx, lu, lxx, luu, lux, lTx, lTxx, gaps, k, K):
    """``(d1 (n,), d2 (n,))``: gradient and curvature of the LQ model along the full step ``du = k + K dx`` with the
    gaps (``dx_{t+1} = A dx + B du + gap_{t+1}``, ``dx_0 = gap_0``), as the array version's."""
    n, T, nx, nu = B.shape[0], B.shape[1], B.shape[2], B.shape[3]
    d1, d2 = np.zeros(n), np.zeros(n)
    dx, du, nxt = np.empty(nx), np.empty(nu), np.empty(nx)
    for i in range(n):
        dx[:] = gaps[i, 0]
        a1, a2 = 0.0, 0.0
        for t in range(T):
            _av(k[i, t], K[i, t], dx, du)
            a1 += _dot(lx[i, t], dx) + _dot(lu[i, t], du)
            a2 += _quad(dx, lxx[i, t], dx) + 2.0 * _quad(du, lux[i, t], dx) + _quad(du, luu[i, t], du)
            _av(gaps[i, t + 1], A[i, t], dx, nxt)
            _av(nxt, B[i, t], du, dx)
        a1 += _dot(lTx[i], dx)
        a2 += _quad(dx, lTxx[i], dx)
        d1[i], d2[i] = a1, a2
    return d1, d2

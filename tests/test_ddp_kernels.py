"""The compiled backward pass and LQ model of box-FDDP (:mod:`sdp_cli.trajopt.ddp_kernels`) and box QP
(:mod:`sdp_cli.trajopt.boxqp`) against their array versions (numpy over the batch, the solver's code until
2026-12-07, kept here verbatim as the oracle) on random problems with clamped controls, and a ``Quu`` that is
not positive definite."""

from __future__ import annotations

import types

import numpy as np
import pytest

from sdp_cli.trajopt.boxqp import ARMIJO, MAX_ITER, MIN_GRAD, MIN_STEP, STEP_DEC, box_qp
from sdp_cli.trajopt.ddp_passes import PassesMixin, _mv


# ---------------------------------------------------------------------------- the array versions (the oracle)
# (with boxqp's own stopping constants, MAX_ITER .. STEP_DEC, imported above)


def _value(H, g, x):
    return 0.5 * np.einsum("ni,nij,nj->n", x, H, x) + np.einsum("ni,ni->n", g, x)


def array_free_solve(H: np.ndarray, rhs: np.ndarray, free: np.ndarray) -> np.ndarray:
    """``X`` with ``H_ff X_f = rhs_f`` and ``X_c = 0`` on the clamped rows: ``H (n, m, m)``, ``rhs (n, m, k)``,
    ``free (n, m)`` bool (the clamped rows and columns of ``H`` are replaced by the identity)."""
    ff = free[:, :, None] & free[:, None, :]
    Hm = np.where(ff, H, 0.0) + np.eye(H.shape[-1]) * (~free)[:, :, None]
    return np.linalg.solve(Hm, np.where(free[:, :, None], rhs, 0.0))


def array_box_qp(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray | None = None):
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
        dx = -array_free_solve(Ha, grad[:, :, None], fr)[:, :, 0]
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


def array_backward(task, T, nx, d, gaps, U, reg):
    """Riccati recursion with gaps and the box QP. Returns ``(k (n,T,nu), K (n,T,nu,nx), Vx (n,T+1,nx),
    free (n,T,nu), stop (n,), ok (n,))``; ``ok`` False where ``Quu + reg I`` is not positive definite."""
    n, nu = len(U), task.nu
    k, K = np.zeros((n, T, nu)), np.zeros((n, T, nu, nx))
    Vx_all = np.zeros((n, T + 1, nx))
    free_all = np.ones((n, T, nu), dtype=bool)
    stop = np.zeros(n)
    ok = np.ones(n, dtype=bool)
    Vx, Vxx = d["lTx"].copy(), d["lTxx"].copy()
    Vx_all[:, T] = Vx
    eye = np.eye(nu)
    for t in reversed(range(T)):
        A, B = d["A"][:, t], d["B"][:, t]
        Vxp = Vx + _mv(Vxx, gaps[:, t + 1])
        At, Bt = A.transpose(0, 2, 1), B.transpose(0, 2, 1)
        Qx = d["lx"][:, t] + _mv(At, Vxp)
        Qu = d["lu"][:, t] + _mv(Bt, Vxp)
        VA, VB = Vxx @ A, Vxx @ B
        Qxx = d["lxx"][:, t] + At @ VA
        Quu = d["luu"][:, t] + Bt @ VB
        Qux = d["lux"][:, t] + Bt @ VA
        Quu_r = 0.5 * (Quu + Quu.transpose(0, 2, 1)) + reg[:, None, None] * eye
        try:                                                     # positive definite (all at once)
            np.linalg.cholesky(Quu_r)
        except np.linalg.LinAlgError:
            pd = np.linalg.eigvalsh(Quu_r)[:, 0] > 0
            ok &= pd
            Quu_r[~pd] = eye                                     # these instances retry with more reg
        lo, hi = task.u_lb - U[:, t], task.u_ub - U[:, t]
        sol = -np.linalg.solve(Quu_r, np.concatenate([Qu[:, :, None], Qux], axis=2))
        kt, Kt = sol[:, :, 0], sol[:, :, 1:]                     # unconstrained step and gain
        free = np.ones((n, nu), dtype=bool)
        out = np.any((kt < lo) | (kt > hi), axis=1)
        if out.any():
            kb, fb, _ = array_box_qp(Quu_r[out], Qu[out], lo[out], hi[out], np.clip(kt[out], lo[out], hi[out]))
            kt[out], free[out] = kb, fb
            Kt[out] = -array_free_solve(Quu_r[out], Qux[out], fb)
        k[:, t], K[:, t], free_all[:, t] = kt, Kt, free
        stop += np.sum(np.where(free, Qu, 0.0) ** 2, axis=1)
        KtT = Kt.transpose(0, 2, 1)
        Vx = Qx + _mv(KtT, _mv(Quu, kt) + Qu) + _mv(Qux.transpose(0, 2, 1), kt)
        Vxx = Qxx + KtT @ Quu @ Kt + KtT @ Qux + Qux.transpose(0, 2, 1) @ Kt
        Vxx = 0.5 * (Vxx + Vxx.transpose(0, 2, 1))
        Vx_all[:, t] = Vx
    return k, K, Vx_all, free_all, stop, ok


def array_model(d, gaps, k, K):
    """``(d1, d2)``: gradient and curvature of the LQ model along the full step (gaps included)."""
    n, T = k.shape[:2]
    dx = gaps[:, 0].copy()
    d1, d2 = np.zeros(n), np.zeros(n)
    for t in range(T):
        du = k[:, t] + _mv(K[:, t], dx)
        d1 += np.einsum("ni,ni->n", d["lx"][:, t], dx) + np.einsum("ni,ni->n", d["lu"][:, t], du)
        d2 += (np.einsum("ni,nij,nj->n", dx, d["lxx"][:, t], dx) + 2 * np.einsum("ni,nij,nj->n", du, d["lux"][:, t], dx)
               + np.einsum("ni,nij,nj->n", du, d["luu"][:, t], du))
        dx = _mv(d["A"][:, t], dx) + _mv(d["B"][:, t], du) + gaps[:, t + 1]
    d1 += np.einsum("ni,ni->n", d["lTx"], dx)
    d2 += np.einsum("ni,nij,nj->n", dx, d["lTxx"], dx)
    return d1, d2


# ---------------------------------------------------------------------------- the tests
def _problem(rng, n, T, nx, nu, bound, indefinite=()):
    A = np.eye(nx) + 0.1 * rng.standard_normal((n, T, nx, nx))
    B = 0.3 * rng.standard_normal((n, T, nx, nu))

    def spd(*s):
        M = rng.standard_normal(s + (s[-1],))
        return M @ np.swapaxes(M, -1, -2) / s[-1] + 0.1 * np.eye(s[-1])
    H = spd(n, T, nx + nu)
    d = dict(A=A, B=B, lx=rng.standard_normal((n, T, nx)), lu=rng.standard_normal((n, T, nu)),
             lxx=H[..., :nx, :nx].copy(), luu=H[..., nx:, nx:].copy(), lux=H[..., nx:, :nx].copy(),
             lTx=rng.standard_normal((n, nx)), lTxx=spd(n, nx))
    for i in indefinite:                       # Quu not positive definite at some t: the instance reports it
        d["luu"][i, T // 2] -= 50 * np.eye(nu)
    task = types.SimpleNamespace(nu=nu, u_lb=-bound * np.ones(nu), u_ub=bound * np.ones(nu))
    return task, d, 0.1 * rng.standard_normal((n, T + 1, nx)), 0.5 * rng.standard_normal((n, T, nu))


@pytest.mark.parametrize("n, T, nx, nu, bound", [(8, 30, 2, 1, 0.2), (6, 40, 4, 2, 0.5), (4, 60, 12, 6, 1.0),
                                                 (4, 60, 12, 4, 5.0)])
def test_compiled_backward_pass_is_the_array_version(n, T, nx, nu, bound):
    """Every output of the compiled pass equals the array version's to rounding, on instances whose steps leave the
    bounds (the box QP and its gains with zero rows) and, at the largest bound, on instances that never do."""
    task, d, gaps, U = _problem(np.random.default_rng(nx * nu), n, T, nx, nu, bound, indefinite=(1,))
    reg = np.full(n, 1e-9)
    want = array_backward(task, T, nx, d, gaps, U, reg)
    got = PassesMixin._backward(types.SimpleNamespace(task=task, T=T, ndx=nx), d, gaps, U, reg)
    ok = want[5]
    assert np.array_equal(got[5], ok) and not ok[1] and ok.sum() == n - 1   # the indefinite Quu is reported
    clamped = ~want[3][ok]
    assert (clamped.mean() > 0.1) if bound < 5 else not clamped.any()
    assert np.array_equal(got[3][ok], want[3][ok])                     # the same clamped controls
    for g, w in zip(got[:5], want[:5]):
        g, w = g[ok].astype(float), w[ok].astype(float)
        assert np.max(np.abs(g - w)) <= 1e-11 * (1 + np.max(np.abs(w)))


def test_compiled_box_qp_is_the_array_version():
    rng = np.random.default_rng(3)
    n, m = 200, 6
    M = rng.standard_normal((n, m, m))
    H = M @ np.swapaxes(M, -1, -2) + 0.05 * np.eye(m)
    g = 3 * rng.standard_normal((n, m))
    lo, hi = -rng.uniform(0.1, 1, (n, m)), rng.uniform(0.1, 1, (n, m))
    x, free, ok = box_qp(H, g, lo, hi)
    xw, fw, okw = array_box_qp(H, g, lo, hi)
    assert ok.all() and okw.all() and (~free).mean() > 0.2
    assert np.array_equal(free, fw) and np.max(np.abs(x - xw)) <= 1e-10


def test_compiled_lq_model_is_the_array_version():
    """d1 and d2 of the full step along the LQ model, with gaps, as the array version's (on the backward pass's own
    steps and gains, clamped rows included)."""
    task, d, gaps, U = _problem(np.random.default_rng(7), 6, 40, 4, 2, 0.5)
    k, K, *_ = array_backward(task, 40, 4, d, gaps, U, np.full(6, 1e-9))
    got = PassesMixin._model(None, d, gaps, k, K)
    want = array_model(d, gaps, k, K)
    for g, w in zip(got, want):
        assert np.max(np.abs(g - w)) <= 1e-12 * (1 + np.max(np.abs(w)))

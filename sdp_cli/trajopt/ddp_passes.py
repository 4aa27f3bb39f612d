"""The passes of box-FDDP's iterations (:class:`sdp_cli.trajopt.ddp.DDPSolver`): the Hessian model, the backward
pass (Riccati recursion with gaps and the box QP), the LQ model's expected change and the line search. See
:mod:`sdp_cli.trajopt.ddp` for the algorithm and its constants."""

from __future__ import annotations

import numpy as np

from sdp_cli.trajopt.boxqp import box_qp, free_solve

#: steps of the line search and the acceptance ratios of a step's actual to its expected change
ALPHAS = tuple(2.0 ** -np.arange(11))
ACCEPT, ACCEPT_NEG = 0.1, 2.0


def _mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product ``(n, i, j), (n, j) -> (n, i)``."""
    return np.matmul(M, v[..., None])[..., 0]


def _psd(M: np.ndarray) -> np.ndarray:
    """Symmetric matrices ``(..., s, s)`` with their negative eigenvalues set to zero (the nearest positive
    semi-definite ones in the Frobenius norm); those already positive semi-definite are returned as they are."""
    M = 0.5 * (M + np.swapaxes(M, -1, -2))
    w, V = np.linalg.eigh(M)
    neg = w[..., 0] < 0
    if not neg.any():
        return M
    out = M.copy()
    out[neg] = (V[neg] * np.maximum(w[neg], 0.0)[..., None, :]) @ np.swapaxes(V[neg], -1, -2)
    return out


def _psd_model(d: dict) -> None:
    """The iterations' Hessian model: each stage's cost Hessian ``[[l_xx, l_ux'], [l_ux, l_uu]]`` and the
    terminal ``l_T,xx`` projected onto the positive semi-definite cone, in place (a Gauss-Newton-like model
    for costs that are not sums of squares: exact Hessians of UR5's end-effector costs are indefinite, which
    made 63 of 136 iterations failed factorizations; crocoddyl's Gauss-Newton model has none)."""
    lxx, luu, lux = d["lxx"], d["luu"], d["lux"]
    nx = lxx.shape[-1]
    H = np.concatenate([np.concatenate([lxx, np.swapaxes(lux, -1, -2)], -1), np.concatenate([lux, luu], -1)], -2)
    H = _psd(H)
    d["lxx"], d["lux"], d["luu"] = H[..., :nx, :nx], H[..., nx:, :nx], H[..., nx:, nx:]
    d["lTxx"] = _psd(d["lTxx"])



class PassesMixin:
    """The backward pass, the LQ model and the line search of :class:`~sdp_cli.trajopt.ddp.DDPSolver` (uses its
    ``task``, ``T``, ``ndx``, ``general`` and ``_rollout``)."""

    def _backward(self, d, gaps, U, reg):
        """Riccati recursion with gaps and the box QP. Returns ``(k (n,T,nu), K (n,T,nu,nx), Vx (n,T+1,nx),
        free (n,T,nu), stop (n,), ok (n,))``; ``ok`` False where ``Quu + reg I`` is not positive definite."""
        task, T = self.task, self.T
        n, nx, nu = len(U), self.ndx, task.nu
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
                kb, fb, _ = box_qp(Quu_r[out], Qu[out], lo[out], hi[out], np.clip(kt[out], lo[out], hi[out]))
                kt[out], free[out] = kb, fb
                Kt[out] = -free_solve(Quu_r[out], Qux[out], fb)
            k[:, t], K[:, t], free_all[:, t] = kt, Kt, free
            stop += np.sum(np.where(free, Qu, 0.0) ** 2, axis=1)
            KtT = Kt.transpose(0, 2, 1)
            Vx = Qx + _mv(KtT, _mv(Quu, kt) + Qu) + _mv(Qux.transpose(0, 2, 1), kt)
            Vxx = Qxx + KtT @ Quu @ Kt + KtT @ Qux + Qux.transpose(0, 2, 1) @ Kt
            Vxx = 0.5 * (Vxx + Vxx.transpose(0, 2, 1))
            Vx_all[:, t] = Vx
        return k, K, Vx_all, free_all, stop, ok

    def _model(self, d, gaps, k, K):
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

    def _line_search(self, X, U, rows, xi, d, gaps, k, K, s, al_state):
        """Try the steps of ``ALPHAS`` on the instances ``rows`` (positions ``s`` in the active arrays); write the
        accepted iterates into ``X``, ``U``. Returns the accepted step per instance (0: none accepted).
        ``al_state``: every instance's ``(lam, rho)``."""
        sub = {key: v[s] for key, v in d.items()}
        lam, rho = al_state
        g, ks, Ks = gaps[s], k[s], K[s]
        d1, d2 = self._model(sub, g, ks, Ks)
        J0 = sub["J"]
        accepted = np.zeros(len(rows))
        pending = np.ones(len(rows), dtype=bool)
        for a in ALPHAS:
            p = np.flatnonzero(pending)
            if not len(p):
                break
            alpha = np.full(len(p), a)
            r = rows[p]
            Xn, Un, J = self._rollout(X[r], U[r], g[p], ks[p], Ks[p], alpha, xi[r],
                                      sub["Jm"][p] if self.general else None, (lam[r], rho[r]))
            expected = -(a * d1[p] + 0.5 * a * a * d2[p])       # the model's decrease
            actual = J0[p] - J
            good = np.isfinite(J) & np.where(expected >= 0, actual >= ACCEPT * expected, actual >= ACCEPT_NEG * expected)
            X[rows[p[good]]], U[rows[p[good]]] = Xn[good], Un[good]
            accepted[p[good]] = a
            pending[p[good]] = False
        return accepted

"""The passes of box-FDDP's iterations (:class:`sdp_cli.trajopt.ddp.DDPSolver`): the Hessian model, the backward
pass (Riccati recursion with gaps and the box QP), the LQ model's expected change and the line search. See
:mod:`sdp_cli.trajopt.ddp` for the algorithm and its constants."""

from __future__ import annotations

import numpy as np

from sdp_cli.trajopt.ddp_kernels import backward, lq_model

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



def _c(a) -> np.ndarray:
    """C-contiguous float64 (the compiled kernels' one signature)."""
    return np.ascontiguousarray(a, dtype=float)


def _lq(d: dict) -> list[np.ndarray]:
    """The LQ model's arrays of the derivatives ``d`` in the kernels' order."""
    return [_c(d[key]) for key in ("A", "B", "lx", "lu", "lxx", "luu", "lux", "lTx", "lTxx")]


class PassesMixin:
    """The backward pass, the LQ model and the line search of :class:`~sdp_cli.trajopt.ddp.DDPSolver` (uses its
    ``task``, ``T``, ``ndx``, ``general`` and ``_rollout``)."""

    def _backward(self, d, gaps, U, reg):
        """Riccati recursion with gaps and the box QP, compiled (:func:`sdp_cli.trajopt.ddp_kernels.backward`).
        Returns ``(k (n,T,nu), K (n,T,nu,nx), Vx (n,T+1,nx), free (n,T,nu), stop (n,), ok (n,))``; ``ok`` False
        where ``Quu + reg I`` is not positive definite."""
        return backward(*_lq(d), _c(gaps), _c(U), _c(self.task.u_lb), _c(self.task.u_ub), _c(reg))

    def _model(self, d, gaps, k, K):
        """``(d1, d2)``: gradient and curvature of the LQ model along the full step (gaps included), compiled
        (:func:`sdp_cli.trajopt.ddp_kernels.lq_model`)."""
        return lq_model(*_lq(d), _c(gaps), _c(k), _c(K))

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

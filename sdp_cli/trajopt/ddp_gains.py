"""The feedback gains of a converged box-FDDP solution (:class:`sdp_cli.trajopt.ddp.DDPSolver`), with the exact
Hessian of the Lagrangian (the DDP itself iterates with Gauss-Newton): the stored ``K_t`` and
``Phi_t = A_t + B_t K_t`` are the sensitivities of the solution, checked against finite differences of re-solves
(``tests/test_ddp.py``)."""

from __future__ import annotations

import time

import numpy as np

from sdp_cli.trajopt import gains as _gains
from sdp_cli.trajopt.ddp_model import ambient_costates
from sdp_cli.trajopt.ddp_model import cols as _cols
from sdp_cli.trajopt.solver import SolveResult


class GainsMixin:
    """The gains of :class:`~sdp_cli.trajopt.ddp.DDPSolver` (uses its compiled functions ``_f`` and ``_map``)."""

    def _add_gains(self, res: SolveResult, Vx: np.ndarray, lin: dict) -> None:
        """Feedback gains at a converged solution with the exact Lagrangian Hessian (co-states ``V_x``; ``lin``:
        ``A``, ``B``, ``lTxx`` of the iteration that found it converged)."""
        t0 = time.perf_counter()
        task, T = self.task, self.T
        X, U, xi = res.X, res.U, res.xi
        lam = -Vx[1:]                                             # d^2 [l + V_x(t+1)' f] = d^2 [l - lam' f]
        H = self._map("sdp_ddp_hess", T)(X[:-1].T, U.T, np.repeat(xi[None], T, 0).T, lam.T)
        s = task.nx + task.nu
        H = _cols(H, T, s, s)
        try:
            K = _gains.riccati_gains_fast(self._f[f"sdp_ddp_riccati_T{T}"], lin["A"], lin["B"], H, lin["lTxx"],
                                          res.clamped)
            if not np.all(np.isfinite(K)):
                raise np.linalg.LinAlgError("non-finite gains")
        except np.linalg.LinAlgError as e:
            res.status += f"; gains unavailable ({e})"
        else:
            res.A, res.B, res.K = lin["A"], lin["B"], K
            res.Phi = res.A + res.B @ K
        res.gain_time = time.perf_counter() - t0

    def _add_general_gains(self, res: SolveResult, mu_h: np.ndarray) -> None:
        """Feedback gains at a converged solution of a :func:`general` task, by fatrop's code
        (:func:`sdp_cli.trajopt.gains.linearize`, active state constraints as equalities of the LQ problem), with
        the ambient multipliers of the gaps (:func:`~sdp_cli.trajopt.ddp_model.ambient_costates`) and those of
        ``h(x_1..x_T)``, ``mu_h (T, n_h)``; active: ``mu > 0`` and ``mu > -h`` (as for fatrop's solutions)."""
        t0 = time.perf_counter()
        task, T, nx = self.task, self.T, self.task.nx
        X, xi = res.X, res.xi
        _, Fx, _, _, lx, *_ = self._map("sdp_ddp_stage", T)(X[:-1].T, res.U.T, np.repeat(xi[None], T, 0).T)
        _, lTx, _ = self._f["sdp_ddp_term"](X[-1], xi)
        h = np.asarray(self._map("sdp_ddp_h", T)(X[1:].T, np.repeat(xi[None], T, 0).T)).T.reshape(T, task.n_h)
        dh = (_cols(self._map("sdp_jac_h", T)(X[1:].T, np.repeat(xi[None], T, 0).T), T, task.n_h, nx) if task.n_h
              else np.zeros((T, 0, nx)))
        lam_gap = ambient_costates(_cols(Fx, T, nx, nx), np.asarray(lx).T, np.asarray(lTx).ravel(), dh, mu_h)
        res.active_h = (mu_h > 0) & (mu_h > -h)
        chart = self._map("sdp_ddp_chart", T + 1)              # (J_+, h, dh): linearize takes (J_+, dh)
        gfun = {"jac_f_map": self._map("sdp_jac_f", T), "hess_stage_map": self._map("sdp_hess_stage", T),
                "hess_term": self._f["sdp_hess_term"], "chart_map": lambda X, xi: chart(X, xi)[::2]}
        _gains.set_solution_gains(res, task, gfun, self._f[f"sdp_ddp_riccati_T{T}"], lam_gap, mu_h)
        res.gain_time = time.perf_counter() - t0

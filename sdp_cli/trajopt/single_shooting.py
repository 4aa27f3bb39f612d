"""Single-shooting transcription of OCP (1), solved by IPOPT: a reporting baseline.

The paper's TO alone is ProxDDP, a DDP-type method: it optimizes the controls only and obtains
the states by rolling the dynamics out, so an initial guess is a control sequence and every
iterate is dynamically feasible. This module poses the same problem that way::

    min_U  sum_t l_t(x_t, u_t; xi) + l_T(x_T; xi)   with  x_{t+1} = f(x_t, u_t),  x_0 = x_hat(xi)
    s.t.   u_lb <= u_t <= u_ub,  h(x_t; xi) <= 0 (t = 1..T)

(``casadi`` ``mapaccum`` of the task's step function, exact Hessian, the same tolerance,
constraint-violation rule and 1000-iteration cap as the multiple-shooting solver). A warm start
uses only the guess's controls, as a DDP warm start does. It returns no gains: collection,
ArgminCost and the stored gains use the multiple-shooting solve (:mod:`sdp_cli.trajopt.solver`);
this solver is the second TO-alone baseline that ``sdp refine --baselines``, ``sdp evaluate`` and
``bench/trajopt.py`` report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from sdp_cli.errors import SdpError

#: solver name recorded in results and reports
NAME = "ss-ipopt"


@dataclass
class ShootingResult:
    """Outcome of one single-shooting solve (the fields the reports need)."""

    X: np.ndarray          # (T+1, nx) rollout of U
    U: np.ndarray          # (T, nu)
    cost: float
    iterations: int
    converged: bool
    solve_time: float
    max_violation: float
    status: str


class SingleShootingSolver:
    """IPOPT on the controls of OCP (1); build with :func:`get_single_shooting`."""

    def __init__(self, task, horizon: int, max_iter: int = 1000, tol: float = 1e-6, viol_tol: float = 1e-6):
        self.task, self.T = task, int(horizon)
        self.max_iter, self.tol, self.viol_tol = int(max_iter), float(tol), float(viol_tol)
        T, nx, nu = self.T, task.nx, task.nu
        U = ca.MX.sym("U", nu, T)
        p = ca.MX.sym("p", nx + task.n_xi)
        x0, xi = p[:nx], p[nx:]
        X = task.f_step.mapaccum("rollout", T)(x0, U)               # (nx, T): x_1 .. x_T
        X_prev = ca.horzcat(x0, X[:, : T - 1])                      # x_0 .. x_{T-1}
        xis = ca.repmat(xi, 1, T)
        f = ca.sum2(task.f_running_cost.map(T)(X_prev, U, xis)) + task.f_terminal_cost(X[:, T - 1], xi)
        g = ca.vec(task.f_state_constraints.map(T)(X, xis)) if task.n_h else ca.MX(0, 1)
        self._ng = int(g.shape[0])
        opts = {"print_time": False, "error_on_fail": False, "show_eval_warnings": False,
                "ipopt": {"print_level": 0, "sb": "yes", "max_iter": self.max_iter, "tol": self.tol,
                          "hessian_approximation": "limited-memory",
                          "acceptable_iter": 0, "constr_viol_tol": 0.1 * self.viol_tol}}
        self._nlpsol = ca.nlpsol(f"sdp_ss_{task.name}_T{T}".replace("-", "_"), "ipopt",
                                 {"x": ca.vec(U), "p": p, "f": f, "g": g}, opts)
        self._rollout = ca.Function("roll", [U, p], [X])

    def solve(self, xi, U_init) -> ShootingResult:
        """Solve from ``x0 = task.initial_state(xi)`` and the control guess ``U_init (T, nu)``."""
        task, T = self.task, self.T
        xi = np.asarray(xi, dtype=float)
        U_init = np.asarray(U_init, dtype=float)
        if U_init.shape != (T, task.nu):
            raise SdpError(f"U_init has shape {U_init.shape}, expected {(T, task.nu)}")
        x0 = task.initial_state(xi)
        p = np.concatenate([x0, xi])
        U0 = np.clip(np.nan_to_num(U_init), task.u_lb, task.u_ub)
        t0 = time.perf_counter()
        r = self._nlpsol(x0=U0.T.ravel(order="F"), p=p, lbx=np.tile(task.u_lb, T), ubx=np.tile(task.u_ub, T),
                         lbg=-np.inf, ubg=0.0)
        stats = self._nlpsol.stats()
        solve_time = time.perf_counter() - t0
        U = np.asarray(r["x"]).reshape(T, task.nu)
        X = np.vstack([x0, np.asarray(self._rollout(U.T, p)).T])
        g = np.asarray(r["g"]).ravel()
        viol = max(float(np.max(g, initial=0.0)), float(np.max(U - task.u_ub, initial=0.0)),
                   float(np.max(task.u_lb - U, initial=0.0)))
        finite = bool(np.all(np.isfinite(X)))
        success = bool(stats.get("success", False))
        converged = success and finite and viol <= self.viol_tol
        status = "converged" if converged else (
            f"not converged: ipopt returned {stats.get('return_status', '?')} after {stats.get('iter_count', 0)} "
            "iterations" if not success else f"not converged: constraint violation {viol:.2e}")
        return ShootingResult(X=X, U=U, cost=float(r["f"]), iterations=int(stats.get("iter_count", 0)),
                              converged=converged, solve_time=solve_time, max_violation=viol, status=status)


_CACHE: dict = {}


def get_single_shooting(task, max_iter: int = 1000) -> SingleShootingSolver:
    """The single-shooting solver of ``task`` on its horizon, built once per process."""
    key = (id(task), task.T, int(max_iter))
    if key not in _CACHE:
        _CACHE[key] = (task, SingleShootingSolver(task, task.T, max_iter))
    return _CACHE[key][1]

"""Finite-difference checks of feedback gains and dynamics Jacobians (tests and bench).

Gains: perturb ``x_t`` of a solved trajectory by ``+-delta`` (through ``task.integrate``),
re-solve the remaining problem from ``t`` (horizon ``T - t``, warm-started from the tail of
the solution), and compare the central difference of ``u_t`` with ``K_t delta``. This is
valid because the costs of every task are time-invariant, so the tail of OCP (1) is the
same OCP on a shorter horizon.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sdp_cli.trajopt.solver import get_solver

#: |du| below this (both FD and K delta) counts as "both zero" (relative error 0)
ZERO_DU = 1e-9


@dataclass
class GainCheck:
    """FD check of ``K_t`` at one step: shapes (nu,)."""

    t: int
    du_fd: np.ndarray
    du_K: np.ndarray
    clamped: np.ndarray  # (nu,) bool
    converged: bool  # both perturbed re-solves converged

    @property
    def rel_error(self) -> float:
        """``||du_fd - K delta|| / max(||du_fd||, ||K delta||)`` (0 if both ~0; NaN if not converged)."""
        if not self.converged:
            return float("nan")
        scale = max(np.linalg.norm(self.du_fd), np.linalg.norm(self.du_K))
        return 0.0 if scale < ZERO_DU else float(np.linalg.norm(self.du_fd - self.du_K) / scale)

    @property
    def clamped_fd(self) -> float:
        """Largest |du_fd| over the clamped controls (should be ~0)."""
        return float(np.max(np.abs(self.du_fd[self.clamped]), initial=0.0))


def check_gains(task, res, steps, eps: float = 1e-4, seed: int = 0, solver: str = "ipopt",
                tol: float = 1e-10, jit: bool = False) -> list[GainCheck]:
    """FD check of ``res.K`` at the given ``steps`` (see the module docstring).

    ``solver``/``tol``/``jit`` configure the reference re-solves (tight IPOPT by default).
    """
    rng = np.random.default_rng(seed)
    out = []
    for t in steps:
        t = int(t)
        sub = get_solver(task, horizon=len(res.U) - t, solver=solver, tol=tol, jit=jit)
        d = rng.standard_normal(task.ndx)
        d *= eps / np.linalg.norm(d)
        Xg, Ug = res.X[t:], res.U[t:]
        up = sub.solve_from(task.integrate(res.X[t], d), res.xi, Xg, Ug, gains=False)
        um = sub.solve_from(task.integrate(res.X[t], -d), res.xi, Xg, Ug, gains=False)
        out.append(GainCheck(t, (up.U[0] - um.U[0]) / 2, res.K[t] @ d, res.clamped[t].copy(),
                             up.converged and um.converged))
    return out


def check_dynamics_jacobians(task, res, steps, eps: float = 1e-6) -> tuple[float, float]:
    """Max relative error of ``res.A``, ``res.B`` vs central differences of ``task.step``
    (Pinocchio), in the tangent space: ``df = f(x (+) e_i eps) (-) f(x)``."""
    errA = errB = 0.0
    for t in steps:
        x, u = res.X[t], res.U[t]
        A = np.empty((task.ndx, task.ndx))
        B = np.empty((task.ndx, task.nu))
        xn = task.step(x, u)
        for i in range(task.ndx):
            e = np.zeros(task.ndx)
            e[i] = eps
            A[:, i] = (task.difference(xn, task.step(task.integrate(x, e), u))
                       - task.difference(xn, task.step(task.integrate(x, -e), u))) / (2 * eps)
        for i in range(task.nu):
            e = np.zeros(task.nu)
            e[i] = eps
            B[:, i] = (task.difference(xn, task.step(x, u + e)) - task.difference(xn, task.step(x, u - e))) / (2 * eps)
        errA = max(errA, np.abs(A - res.A[t]).max() / max(1.0, np.abs(A).max()))
        errB = max(errB, np.abs(B - res.B[t]).max() / max(1.0, np.abs(B).max()))
    return errA, errB

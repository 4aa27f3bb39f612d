"""Multiple-shooting transcription of OCP (1) as a parametric casadi NLP.

Decision variables, stage-wise (the order fatrop's structure needs, fine for IPOPT too)::

    w = [x_0, u_0, x_1, u_1, ..., x_{T-1}, u_{T-1}, x_T]            (T+1) nx + T nu

Constraints ``g``, stage-wise: the gap ``x_{k+1} - f(x_k, u_k)`` of stage k, then the path
constraints of stage k (stage 0: ``x_0 - x0_hat``; stage k >= 1: ``h(x_k; xi)``), and
finally ``h(x_T; xi)``::

    g = [gap_0, x_0 - x0_hat, gap_1, h(x_1), ..., gap_{T-1}, h(x_{T-1}), h(x_T)]

Gaps and ``x_0`` are equalities (``lbg = ubg = 0``), ``h <= 0``. Control bounds are
variable bounds. Parameters ``p = [x0_hat (nx), xi (n_xi)]``: a new task instance or
initial state changes only numbers, never the NLP.

The NLP is built from ``map``-ped stage functions in an MX graph, so its generated C code
(see :mod:`sdp_cli.trajopt.jit`) is one loop per stage function, whatever ``T``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np


@dataclass(frozen=True)
class Layout:
    """Index bookkeeping of ``w`` and ``g`` for horizon ``T``."""

    T: int
    nx: int
    nu: int
    n_h: int

    @property
    def nw(self) -> int:
        return (self.T + 1) * self.nx + self.T * self.nu

    @property
    def ng(self) -> int:
        return (self.T + 1) * self.nx + self.T * self.n_h

    def x_index(self) -> np.ndarray:
        """(T+1, nx) positions of the states in ``w``."""
        s = self.nx + self.nu
        return np.arange(self.T + 1)[:, None] * s + np.arange(self.nx)[None]

    def u_index(self) -> np.ndarray:
        """(T, nu) positions of the controls in ``w``."""
        s = self.nx + self.nu
        return np.arange(self.T)[:, None] * s + self.nx + np.arange(self.nu)[None]

    def g_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row positions in ``g``: gaps (T, nx), init (nx,), h of x_1..x_T (T, n_h)."""
        nx, n_h, T = self.nx, self.n_h, self.T
        gap, h = np.zeros((T, nx), dtype=int), np.zeros((T, n_h), dtype=int)
        gap[0] = np.arange(nx)
        init = nx + np.arange(nx)
        r = 2 * nx
        for t in range(1, T):
            gap[t] = r + np.arange(nx)
            h[t - 1] = r + nx + np.arange(n_h)
            r += nx + n_h
        h[T - 1] = r + np.arange(n_h)
        return gap, init, h

    def equality(self) -> np.ndarray:
        """(ng,) bool: which rows of ``g`` are equalities."""
        eq = np.ones(self.ng, dtype=bool)
        eq[self.g_index()[2].ravel()] = False
        return eq

    def pack(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        w = np.empty(self.nw)
        w[self.x_index()] = X
        w[self.u_index()] = U
        return w

    def unpack(self, w) -> tuple[np.ndarray, np.ndarray]:
        w = np.asarray(w, dtype=float).ravel()
        return w[self.x_index()], w[self.u_index()]

    def fatrop_structure(self) -> dict:
        """The ``N, nx, nu, ng`` options of fatrop's manual structure detection."""
        T = self.T
        return {"structure_detection": "manual", "N": T, "nx": [self.nx] * (T + 1),
                "nu": [self.nu] * T + [0], "ng": [self.nx] + [self.n_h] * T}


def build_nlp(task, T: int) -> tuple[dict, Layout]:
    """The NLP ``{"x": w, "p": p, "f": J, "g": g}`` of the task on horizon ``T`` (MX graph)."""
    nx, nu, n_h = task.nx, task.nu, task.n_h
    lay = Layout(T, nx, nu, n_h)
    w = ca.MX.sym("w", lay.nw)
    p = ca.MX.sym("p", nx + task.n_xi)
    x0_hat, xi = p[:nx], p[nx:]
    XU = ca.reshape(w[: T * (nx + nu)], nx + nu, T)
    X, U = XU[:nx, :], XU[nx:, :]
    xT = w[T * (nx + nu):]
    Xn = ca.horzcat(X[:, 1:], xT)  # x_1 .. x_T
    xis = ca.repmat(xi, 1, T)
    gap = Xn - task.f_step.map(T)(X, U)
    J = ca.sum2(task.f_running_cost.map(T)(X, U, xis)) + task.f_terminal_cost(xT, xi)
    parts = [gap[:, 0], X[:, 0] - x0_hat]
    if n_h:
        Hn = task.f_state_constraints.map(T)(Xn, xis)  # h(x_1) .. h(x_T)
        if T > 1:
            parts.append(ca.vec(ca.vertcat(gap[:, 1:], Hn[:, : T - 1])))
        parts.append(Hn[:, T - 1])
    elif T > 1:
        parts.append(ca.vec(gap[:, 1:]))
    return {"x": w, "p": p, "f": J, "g": ca.vertcat(*parts)}, lay

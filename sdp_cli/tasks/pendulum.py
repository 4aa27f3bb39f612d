"""Pendulum swing-up tasks: ``pendulum`` (1 joint) and ``double_pendulum`` (2 joints).

Model: example-robot-data's ``double_pendulum`` (two small links, joints about x), with a
``tip`` frame added at the end of the second link (0.22 m above joint 2, the end of the
link mesh). The single pendulum is the same model with joint 2 locked at 0
(``pin.buildReducedModel``), so its tip is 0.32 m from joint 1.

q = 0 is the upright configuration. P: q0 is drawn around the downward position
(joint 1 uniform in [pi - 0.5, pi + 0.5], joint 2 uniform in [-0.5, 0.5]), v0 = 0;
xi = x0 (nx,). Actuated joints have |u| <= 25: both for ``double_pendulum``; only joint 1
for ``double_pendulum-pendubot``, only joint 2 for ``double_pendulum-acrobot`` (crocoddyl's
``ActuationModelDoublePendulum`` with ``actLink`` 1 or 2), where u (1,) maps to tau = S u.

The fully actuated double pendulum is easy for the optimizer (about 20 iterations, every
solve converges, mean cost about 12 on our test set): the links are light (|M| ~ 0.015 kg m^2)
and the solution whips them up within a few steps. The paper's figures (TO alone: mean cost
50, ~900 iterations, 80% failures) are closer to the underactuated variants. bench/trajopt.py,
20 instances from the naive guess (fatrop): fully actuated 22.8 iterations, mean cost 12.9;
pendubot 60.6 iterations, 35.6; acrobot 210 iterations (some near the 1000 cap), 36.3.

Costs (summed per step, not multiplied by dt), ee = tip position, goal = tip at q = 0:
    l_t = 10 ||ee(x_t) - goal||^2 + 0.1 ||u_t||^2
    l_T = 100 ||ee(x_T) - goal||^2 + 1.0 ||v_T||^2   (our choice: hold the upright pose)
Naive guess: q linearly interpolated from q0 to the nearest upright configuration
(multiples of 2 pi), v the constant velocity of that line, u = 0.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin

from sdp_cli.errors import SdpError
from sdp_cli.tasks.base import Task
from sdp_cli.tasks.robots import load_model

U_MAX = 25.0
TIP_OFFSET = 0.22  # m, along z of link 2
W_GOAL, W_U, W_GOAL_T, W_V_T = 10.0, 0.1, 100.0, 1.0


def pendulum_model(n_links: int) -> pin.Model:
    """The double pendulum with a ``tip`` frame; joint 2 locked at 0 if ``n_links == 1``."""
    model = load_model("double_pendulum")
    j2 = model.getJointId("joint2")
    model.addFrame(pin.Frame("tip", j2, pin.SE3(np.eye(3), np.array([0.0, 0.0, TIP_OFFSET])),
                             pin.FrameType.OP_FRAME))
    if n_links == 1:
        model = pin.buildReducedModel(model, [j2], pin.neutral(model))
    return model


class PendulumTask(Task):
    """Swing a single or double pendulum from a random downward position to upright."""

    def __init__(self, n_links: int = 2, T: int = 100, dt: float = 0.02,
                 init_spread: float = 0.5, actuated: tuple | None = None, name: str | None = None):
        if n_links not in (1, 2):
            raise SdpError(f"n_links must be 1 or 2, got {n_links}")
        actuated = tuple(range(n_links)) if actuated is None else tuple(int(j) for j in actuated)
        if not actuated or len(set(actuated)) != len(actuated) or not set(actuated) <= set(range(n_links)):
            raise SdpError(f"actuated must list distinct joint indices in 0..{n_links - 1}, got {list(actuated)}")
        if T < 2:
            raise SdpError(f"horizon T must be >= 2, got {T}")
        if not dt > 0:
            raise SdpError(f"dt must be > 0, got {dt}")
        self.name = name or ("pendulum" if n_links == 1 else "double_pendulum")
        self.n_links, self.T, self.dt, self.init_spread = n_links, int(T), float(dt), float(init_spread)
        self.actuated = actuated
        self.model = pendulum_model(n_links)
        super().__init__()
        self.nu = len(actuated)
        self.S = np.zeros((self.nv, self.nu))  # tau = S u
        self.S[list(actuated), range(self.nu)] = 1.0
        self.n_xi = self.nx
        self.u_lb, self.u_ub = -U_MAX * np.ones(self.nu), U_MAX * np.ones(self.nu)
        self.tip = self.model.getFrameId("tip")
        pin.framesForwardKinematics(self.model, self.data, np.zeros(self.nq))
        self.goal = self.data.oMf[self.tip].translation.copy()

    def params(self) -> dict:
        out = {**super().params(), "n_links": self.n_links, "init_spread": self.init_spread}
        if self.nu < self.nv:  # (kept out of fully actuated tasks' params: their artifacts stay valid)
            out["actuated"] = list(self.actuated)
        return out

    def _control_to_tau(self, u):
        return u if self.nu == self.nv else ca.mtimes(ca.DM(self.S), u)

    def control_to_tau(self, u: np.ndarray) -> np.ndarray:
        return self.S @ np.asarray(u, dtype=float)

    def sample_xi(self, rng: np.random.Generator) -> np.ndarray:
        q0 = rng.uniform(-self.init_spread, self.init_spread, self.nq)
        q0[0] += np.pi
        return np.concatenate([q0, np.zeros(self.nv)])

    def initial_state(self, xi: np.ndarray) -> np.ndarray:
        return np.asarray(xi, dtype=float).copy()

    def naive_guess(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x0 = self.initial_state(xi)
        q0 = x0[: self.nq]
        q_tgt = 2 * np.pi * np.round(q0 / (2 * np.pi))
        s = np.linspace(0.0, 1.0, self.T + 1)[:, None]
        Q = q0 + s * (q_tgt - q0)
        V = np.repeat(((q_tgt - q0) / (self.T * self.dt))[None], self.T + 1, 0)
        V[0] = x0[self.nq:]
        return np.hstack([Q, V]), np.zeros((self.T, self.nu))

    def goal_distance(self, x: np.ndarray, xi: np.ndarray) -> float:
        """Tip distance to the upright tip position (m)."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(x[: self.nq], float))
        return float(np.linalg.norm(self.data.oMf[self.tip].translation - self.goal))

    def ee_position(self, q):
        """casadi tip position (3,)."""
        return self.cmodel.frame_placement(q, self.tip)[1]

    def _running_cost(self, x, u, xi):
        e = self.ee_position(x[: self.nq]) - self.goal
        return W_GOAL * ca.sumsqr(e) + W_U * ca.sumsqr(u)

    def _terminal_cost(self, x, xi):
        e = self.ee_position(x[: self.nq]) - self.goal
        return W_GOAL_T * ca.sumsqr(e) + W_V_T * ca.sumsqr(x[self.nq:])

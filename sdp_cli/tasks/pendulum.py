"""Pendulum swing-up tasks: ``pendulum`` (1 link) and ``double_pendulum`` (2 links), the paper's.

Model (source: aligator ``examples/pendulum.py``, ``create_pendulum(N)``, re-implemented with
Pinocchio alone): N revolute joints about x; each body is a 1 kg sphere of radius 0.1 m placed
1 m along +z from its joint; joint k+1 sits at body k; an ``end_effector`` frame at the last
body. q = 0 is upright (gravity along -z). With two links, joint 1 needs 29.4 N m to hold the
straight arm horizontal, so the bound |u| <= 25 (paper, Sec. IV-C) is active in every solution.

Costs (source: aligator's ``QuadraticResidualCost`` = 1/2 r^T W r, running weights multiplied by
dt as in the example; weights of the paper's pendulums), ee = end-effector position, goal = ee
at q = 0, i.e. (0, 0, N):
    l_t = dt * 1/2 (10 ||ee(x_t) - goal||^2 + 0.1 ||u_t||^2)
    l_T = 1/2 * 10 ||ee(x_T) - goal||^2           (no dt, no velocity term)
dt = 0.01 s, T = 100 (aligator example: dt 0.01).

P (ours, as before): q0 around the downward position, joint 1 uniform in [pi - 0.5, pi + 0.5],
joint 2 uniform in [-0.5, 0.5], v0 = 0; xi = x0 (nx,).
Naive guess (ours): q linearly interpolated from q0 to the nearest upright configuration
(multiples of 2 pi), v the constant velocity of that line, u = 0.
Success (ours, stated before any run): the end effector within ``GOAL_TOLERANCE`` = 0.1 m of
the goal at T (5% of the double pendulum's 2 m reach).

``PendulumTask(actuated=...)`` builds underactuated variants (u (1,) mapped to tau = S u); none is
registered: on this model with |u| <= 25 on one joint, fatrop fails from the naive guess.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin

from sdp_cli.errors import SdpError
from sdp_cli.tasks.base import Task

U_MAX = 25.0            # N m, paper Sec. IV-C
BODY_MASS, BODY_RADIUS, LINK_LENGTH = 1.0, 0.1, 1.0   # aligator create_pendulum
W_GOAL, W_U, W_GOAL_T = 10.0, 0.1, 10.0               # paper / aligator-style 1/2 r^T W r
GOAL_TOLERANCE = 0.1    # m (ours)
EE_FRAME = "end_effector"


def create_pendulum(n_links: int) -> pin.Model:
    """aligator's ``create_pendulum(N)``: a chain of N point-like 1 kg spheres on 1 m massless links."""
    model = pin.Model()
    parent, placement = 0, pin.SE3.Identity()
    body = pin.SE3(np.eye(3), np.array([0.0, 0.0, LINK_LENGTH]))
    for k in range(n_links):
        joint = model.addJoint(parent, pin.JointModelRX(), placement, f"joint_{k + 1}")
        model.appendBodyToJoint(joint, pin.Inertia.FromSphere(BODY_MASS, BODY_RADIUS), body)
        model.effortLimit[joint - 1] = U_MAX
        parent, placement = joint, body
    model.addFrame(pin.Frame(EE_FRAME, parent, 0, body, pin.FrameType.OP_FRAME))
    return model


class PendulumTask(Task):
    """Swing a single or double pendulum from a random downward position to upright."""

    goal_tolerance = GOAL_TOLERANCE

    def __init__(self, n_links: int = 2, T: int = 100, dt: float = 0.01,
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
        self.reference_solve_s = (0.002, 0.18) if n_links == 1 else (0.010, 0.155)   # results/tasks/TO_alone.md
        self.reference_ddp_s = 0.002 if n_links == 1 else 0.045
        self.n_links, self.T, self.dt, self.init_spread = n_links, int(T), float(dt), float(init_spread)
        self.actuated = actuated
        self.model = create_pendulum(n_links)
        super().__init__()
        self.nu = len(actuated)
        self.S = np.zeros((self.nv, self.nu))  # tau = S u
        self.S[list(actuated), range(self.nu)] = 1.0
        self.actuation = None if self.nu == self.nv else self.S
        self.n_xi = self.nx
        self.u_lb, self.u_ub = -U_MAX * np.ones(self.nu), U_MAX * np.ones(self.nu)
        self.tip = self.model.getFrameId(EE_FRAME)
        pin.framesForwardKinematics(self.model, self.data, np.zeros(self.nq))
        self.goal = self.data.oMf[self.tip].translation.copy()

    def params(self) -> dict:
        out = {**super().params(), "n_links": self.n_links, "init_spread": self.init_spread}
        if self.nu < self.nv:  # (kept out of fully actuated tasks' params: their artifacts stay valid)
            out["actuated"] = list(self.actuated)
        return out

    def goal_point(self, xi: np.ndarray) -> np.ndarray:
        """The upright tip position (3,), the same for every instance."""
        return self.goal.copy()

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
        """End-effector distance to the upright end-effector position (m)."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(x[: self.nq], float))
        return float(np.linalg.norm(self.data.oMf[self.tip].translation - self.goal))

    def ee_position(self, q):
        """casadi end-effector position (3,)."""
        return self.cmodel.frame_placement(q, self.tip)[1]

    def _running_cost(self, x, u, xi):
        e = self.ee_position(x[: self.nq]) - self.goal
        return self.dt * 0.5 * (W_GOAL * ca.sumsqr(e) + W_U * ca.sumsqr(u))

    def _terminal_cost(self, x, xi):
        e = self.ee_position(x[: self.nq]) - self.goal
        return 0.5 * W_GOAL_T * ca.sumsqr(e)

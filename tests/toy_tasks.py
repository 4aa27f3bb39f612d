"""A user's task, written against sdp's Task interface only (this file is also the source of the temporary
modules of tests/test_task_plugins.py, so it imports nothing from the test suite)."""

import numpy as np
import pinocchio as pin

from sdp_cli.tasks.base import Task


class TurntableTask(Task):
    """A 1 kg mass at 0.5 m on a turntable (revolute joint about the vertical: no gravity torque), turned by
    a bounded torque from a random angle to a goal angle: ``xi = (q0, v0, q_goal)``;
    ``l_t = dt 1/2 (10 (q - q_goal)^2 + 0.1 u^2)``, ``l_T = 1/2 10 (q_T - q_goal)^2``."""

    goal_tolerance = 0.05

    def __init__(self, T: int = 40, dt: float = 0.02, name: str = "toy-turntable"):
        model = pin.Model()
        j = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "turn")
        arm = pin.SE3(np.eye(3), np.array([0.5, 0.0, 0.0]))
        model.appendBodyToJoint(j, pin.Inertia.FromSphere(1.0, 0.1), arm)
        model.addFrame(pin.Frame("mass", j, 0, arm, pin.FrameType.OP_FRAME))
        self.model, self.name, self.T, self.dt = model, name, T, dt
        super().__init__()
        self.nu, self.n_xi = 1, 3
        self.u_lb, self.u_ub = np.array([-2.0]), np.array([2.0])

    def sample_xi(self, rng):
        return np.array([rng.uniform(-1, 1), 0.0, rng.uniform(-1, 1)])

    def initial_state(self, xi):
        return np.asarray(xi[:2], dtype=float).copy()

    def naive_guess(self, xi):
        X = np.zeros((self.T + 1, 2))
        X[:, 0] = np.linspace(xi[0], xi[2], self.T + 1)
        return X, np.zeros((self.T, 1))

    def _running_cost(self, x, u, xi):
        return self.dt * 0.5 * (10 * (x[0] - xi[2]) ** 2 + 0.1 * u[0] ** 2)

    def _terminal_cost(self, x, xi):
        return 0.5 * 10 * (x[0] - xi[2]) ** 2

    def goal_distance(self, x, xi):
        return float(abs(x[0] - xi[2]))

    def goal_point(self, xi):
        return 0.5 * np.array([np.cos(xi[2]), np.sin(xi[2]), 0.0])

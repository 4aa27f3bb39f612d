"""The Task contract (sdp_cli.tasks.base.Task), checked on every registered task and every action it
accepts, and on a toy task added by one class and one registration: the casadi step equals Pinocchio's,
the observation and action maps' Jacobians equal finite differences on the state manifold, actions read
off a trajectory give back its controls, the batched rollout step equals the one-by-one simulation, the
cost and constraints evaluate, and the scene a plot needs is there."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.data.chunks import action_sequence, task_with_action
from sdp_cli.rollout import step_batch
from sdp_cli.tasks import _REGISTRY, get_task, register, task_names
from sdp_cli.tasks.base import Task

#: Jacobian entries are O(1); the quadrotor's (Pinocchio's Jlog6 of a rotation within ~1e-4 rad of the
#: reference) match finite differences to 2.5e-6, every other task's to < 1e-8
JAC_ATOL = 1e-5
CASES = [(name, a) for name in task_names() for a in get_task(name).accepted_actions]


def _trajectory(task, n=10, seed=0):
    """``X (n+1, nx)``, ``U (n, nu)``: smooth controls inside the bounds from a sampled x0."""
    rng = np.random.default_rng(seed)
    xi = task.sample_xi(rng)
    mid, half = (task.u_ub + task.u_lb) / 2, (task.u_ub - task.u_lb) / 2
    U = mid + 0.02 * half * np.sin(0.3 * np.arange(n)[:, None] + rng.uniform(0, 2 * np.pi, task.nu))
    return xi, task.simulate(task.initial_state(xi), U), U


def _fd(task, f, x, eps=1e-4):
    """Central differences of ``f`` on the manifold: ``(f(x (+) e_i eps) - f(x (-) e_i eps)) / 2 eps``
    (eps 1e-4: near the identity rotation Pinocchio's log map switches to its Taylor branch, and steps
    of 1e-6 across that switch are off by ~1e-6)."""
    cols = []
    for i in range(task.ndx):
        e = np.zeros(task.ndx)
        e[i] = eps
        cols.append((f(task.integrate(x, e)) - f(task.integrate(x, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def check_task(task: Task) -> None:
    xi, X, U = _trajectory(task)
    assert xi.shape == (task.n_xi,) and X.shape == (len(U) + 1, task.nx)
    assert task.u_lb.shape == task.u_ub.shape == (task.nu,) and np.all(task.u_lb < task.u_ub)
    assert task.actuation is None or np.shape(task.actuation) == (task.nv, task.nu)
    # casadi step (the optimizer's) == Pinocchio step (the simulation's), and the batched step of rollouts
    for t in (0, len(U) // 2, len(U) - 1):
        np.testing.assert_allclose(np.asarray(task.f_step(X[t], U[t])).ravel(), X[t + 1], atol=1e-9)
    np.testing.assert_allclose(step_batch(task, X[:-1], U), X[1:], atol=1e-9)
    # control-to-torque: one definition for casadi and numpy
    u = U[1]
    np.testing.assert_allclose(np.asarray(ca.evalf(task._control_to_tau(ca.DM(u)))).ravel(),
                               task.control_to_tau(u), atol=1e-12)
    # observation map and its Jacobian in the state tangent
    x = X[len(X) // 2]
    assert task.observation(x).shape == (task.n_obs,)
    np.testing.assert_allclose(task.observation_jacobian(x), _fd(task, task.observation, x), atol=JAC_ATOL)
    # OCP pieces evaluate; the naive guess has the right shapes
    X0, U0 = task.naive_guess(xi)
    assert X0.shape == (task.T + 1, task.nx) and U0.shape == (task.T, task.nu)
    assert np.isfinite(task.cost(X0, U0, xi)) and np.isfinite(task.constraint_violation(X0, U0, xi))
    assert np.isfinite(task.goal_distance(X[-1], xi))
    # scene
    assert task.path_points(X).shape == (len(X), 3)
    g = task.goal_point(xi)
    assert g is None or np.shape(g) == (3,)
    assert np.asarray(task.columns).reshape(-1, 3).shape[1] == 3 and task.column_margin >= 0


def check_action(task: Task, action: str) -> None:
    task = task_with_action(task, action)
    xi, X, U = _trajectory(task, seed=1)
    if action == "u":
        A = U
    else:
        x = X[3]
        assert task.state_action(x).shape == (task.n_action,)
        np.testing.assert_allclose(task.state_action_jacobian(x), _fd(task, task.state_action, x), atol=JAC_ATOL)
        A = action_sequence(task, X, U, action)[1:]
    np.testing.assert_allclose(task.controls_from_action(X[:-1], A), U, atol=1e-7, rtol=1e-7)


@pytest.mark.parametrize("name", task_names())
def test_registered_task_meets_the_contract(name):
    check_task(get_task(name))


@pytest.mark.parametrize("name,action", CASES, ids=[f"{n}-{a}" for n, a in CASES])
def test_registered_task_accepted_action_meets_the_contract(name, action):
    check_action(get_task(name), action)


# ------------------------------------------------------------------ a task added by one class
class TurntableTask(Task):
    """A 1 kg mass at 0.5 m on a turntable (revolute joint about the vertical: no gravity torque), turned by
    a bounded torque from a random angle to a goal angle: ``xi = (q0, v0, q_goal)``;
    ``l_t = dt 1/2 (10 (q - q_goal)^2 + 0.1 u^2)``, ``l_T = 1/2 10 (q_T - q_goal)^2``."""

    goal_tolerance = 0.05

    def __init__(self, T: int = 40, dt: float = 0.02):
        model = pin.Model()
        j = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "turn")
        arm = pin.SE3(np.eye(3), np.array([0.5, 0.0, 0.0]))
        model.appendBodyToJoint(j, pin.Inertia.FromSphere(1.0, 0.1), arm)
        model.addFrame(pin.Frame("mass", j, 0, arm, pin.FrameType.OP_FRAME))
        self.model, self.name, self.T, self.dt = model, "toy-turntable", T, dt
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


@pytest.fixture()
def toy_task():
    register("toy-turntable", lambda **kw: TurntableTask(**kw), "a mass on a turntable (test)")
    yield get_task("toy-turntable")
    _REGISTRY.pop("toy-turntable", None)


def test_a_task_added_by_one_class_meets_the_contract_and_runs_in_sdp(toy_task, tmp_path):
    check_task(toy_task)
    for action in toy_task.accepted_actions:
        check_action(toy_task, action)
    assert toy_task.accepted_actions == ("u", "x", "q", "v")
    r = CliRunner().invoke(app, ["collect", "--task", "toy-turntable", "--n-traj", "2", "--seed", "0", "--workers", "1",
                                 "--out", str(tmp_path / "d.npz")])
    assert r.exit_code == 0, r.output
    arrays, meta = load_npz(tmp_path / "d.npz", kind="dataset")
    assert meta["task"] == "toy-turntable" and arrays["converged"].all()
    assert np.abs(arrays["X"][:, -1, 0] - arrays["xi"][:, 2]).max() < 0.05     # the mass reaches its goal angle
    np.testing.assert_allclose(toy_task.path_points(arrays["X"][0])[-1], toy_task.goal_point(arrays["xi"][0]),
                               atol=0.05)

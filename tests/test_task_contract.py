"""The Task contract (sdp_cli.tasks.base.Task), checked on every registered task and every action it
accepts, and on a toy task added by one class and one registration: the casadi step equals Pinocchio's,
the observation and action maps' Jacobians equal finite differences on the state manifold, actions read
off a trajectory give back its controls, the batched rollout step equals the one-by-one simulation, the
cost and constraints evaluate, and the scene a plot needs is there."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.tasks import _REGISTRY, get_task, register, task_names
from sdp_cli.tasks.base import Task
from sdp_cli.tasks.contract import action_rows, model_rows

CASES = [(name, a) for name in task_names() for a in get_task(name).accepted_actions]


def failed(rows):
    return [r for r in rows if not r["ok"]]


def check_task(task: Task) -> None:
    """The checks `sdp check-task --no-solve` runs (sdp_cli.tasks.contract.model_rows)."""
    assert not failed(model_rows(task)), failed(model_rows(task))


def check_action(task: Task, action: str) -> None:
    assert not failed(action_rows(task, action)), failed(action_rows(task, action))


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


def test_check_task_cli_passes_on_the_toy_task_and_fails_a_broken_one(toy_task, monkeypatch):
    """`sdp check-task`: a pass/fail table; a task whose observation Jacobian is wrong fails with exit 1."""
    r = CliRunner().invoke(app, ["check-task", "toy-turntable", "--cases", "8:4"])
    assert r.exit_code == 0 and "passes all" in r.output and "memorizer (T_h 8, T_a 4)" in r.output, r.output
    monkeypatch.setattr(type(toy_task), "observation_jacobian", lambda self, x: 2 * np.eye(2) + 0 * x[..., None])
    r = CliRunner().invoke(app, ["check-task", "toy-turntable", "--no-solve"])
    assert r.exit_code == 1 and "FAIL  observation Jacobian vs FD" in r.output

"""The Task contract (sdp_cli.tasks.base.Task), checked on every registered task and every action it
accepts, and on a toy task added by one class and one registration: the casadi step equals Pinocchio's,
the observation and action maps' Jacobians equal finite differences on the state manifold, actions read
off a trajectory give back its controls, the batched rollout step equals the one-by-one simulation, the
cost and constraints evaluate, and the scene a plot needs is there."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.tasks import _REGISTRY, get_task, register, task_names
from sdp_cli.tasks.base import Task
from sdp_cli.checks.contract import action_rows, model_rows
from toy_tasks import TurntableTask

CASES = [(name, a) for name in task_names() for a in get_task(name).accepted_actions]


def failed(rows):
    return [r for r in rows if not r["ok"]]


def check_task(task: Task) -> None:
    """The checks `sdp check-task --no-solve` runs (sdp_cli.checks.contract.model_rows)."""
    assert not failed(model_rows(task)), failed(model_rows(task))


def check_action(task: Task, action: str) -> None:
    assert not failed(action_rows(task, action)), failed(action_rows(task, action))


@pytest.mark.parametrize("name", task_names())
def test_registered_task_meets_the_contract(name):
    check_task(get_task(name))


@pytest.mark.parametrize("name,action", CASES, ids=[f"{n}-{a}" for n, a in CASES])
def test_registered_task_accepted_action_meets_the_contract(name, action):
    check_action(get_task(name), action)


# ------------------------------------------------------------------ a task added by one class (tests/toy_tasks.py)
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

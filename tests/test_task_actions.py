"""Every registered task and every action variable it accepts: actions read off a trajectory of
the dynamics give back its controls and states (the rollout's inverse-dynamics path), and
actions a task does not accept are refused at ``sdp train`` in one line."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.chunks import action_sequence, task_with_action
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task, task_names

CASES = [(name, a) for name in task_names() for a in get_task(name).accepted_actions]


def _trajectory(task, n=12, seed=0):
    """``X (n+1, nx)``, ``U (n, nu)``: controls inside the bounds, smooth in time, from a sampled x0."""
    rng = np.random.default_rng(seed)
    x0 = task.initial_state(task.sample_xi(rng))
    mid, half = (task.u_ub + task.u_lb) / 2, (task.u_ub - task.u_lb) / 2
    t = np.arange(n)[:, None]
    U = mid + 0.02 * half * np.sin(0.3 * t + rng.uniform(0, 2 * np.pi, task.nu))
    X = task.simulate(x0, U)
    assert np.abs(X[:, task.nq:]).max() < 50, "the test trajectory should stay physical"
    return X, U


def test_every_task_accepts_its_default_action_and_torque():
    for name in task_names():
        task = get_task(name)
        assert task.action in task.accepted_actions and "u" in task.accepted_actions


@pytest.mark.parametrize("name,action", CASES, ids=[f"{n}-{a}" for n, a in CASES])
def test_actions_from_a_trajectory_reproduce_its_controls_and_states(name, action):
    task = task_with_action(get_task(name), action)
    X, U = _trajectory(task)
    if action == "u":
        A = U
    else:
        A = action_sequence(task, X, U, action)[1:]      # a_t = g(x_{t+1}), t = 0..n-1
    U_back = task.controls_from_action(X[:-1], A)        # batched over time
    np.testing.assert_allclose(U_back, U, atol=1e-7, rtol=1e-7)
    X_back = task.simulate(X[0], U_back)
    np.testing.assert_allclose(X_back, X, atol=1e-7)
    # one state at a time gives the same controls
    np.testing.assert_allclose(task.controls_from_action(X[3], A[3]), U[3], atol=1e-7, rtol=1e-7)


def test_unaccepted_action_is_refused(tmp_path):
    from sdp_cli.tasks.pendulum import PendulumTask

    with pytest.raises(SdpError, match="accepts actions u; got 'x'"):
        task_with_action(PendulumTask(n_links=2, actuated=(1,), name="acrobot-test"), "x")   # underactuated
    with pytest.raises(SdpError, match="accepts actions x, u; got 'q'"):
        task_with_action(get_task("quadrotor-0"), "q")
    from synthetic_dataset import write_dataset

    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=1, T=20)
    r = CliRunner().invoke(app, ["train", "--data", str(data), "--method", "dp", "--epochs", "1", "--horizon", "8",
                                 "--down-dims", "8,16", "--action", "w", "--out", str(tmp_path / "run"),
                                 "--no-progress"])
    assert r.exit_code == 1 and "accepts actions u, x, q, v" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "run").exists()

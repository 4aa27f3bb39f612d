"""Pendulum tasks: aligator's ``create_pendulum(N)`` and the paper's costs, against hand computations."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.pendulum import PendulumTask


@pytest.mark.parametrize("name,n", [("pendulum", 1), ("double_pendulum", 2)])
def test_model_is_create_pendulum(name, n):
    task = get_task(name)
    assert task.nq == task.nv == task.nu == n and task.dt == 0.01 and task.T == 100
    assert [float(i.mass) for i in task.model.inertias[1:]] == [1.0] * n
    np.testing.assert_allclose(task.goal, [0, 0, n])             # upright: bobs at 1 m, 2 m along +z
    q = np.full(n, np.pi / 2)                                       # joint 1 horizontal, straight arm
    q[1:] = 0
    tau = pin.rnea(task.model, task.data, q, np.zeros(n), np.zeros(n))
    # gravity torque of the straight horizontal arm: 9.81 * (1 + 2) N m on joint 1 for two links
    assert abs(tau[0]) == pytest.approx(9.81 * sum(range(1, n + 1)), rel=1e-3)
    assert task.u_ub.tolist() == [25.0] * n
    if n == 2:
        assert abs(tau[0]) > task.u_ub[0]                            # the bound binds the swing-up


def test_costs_are_the_papers():
    task = get_task("double_pendulum")
    rng = np.random.default_rng(0)
    x, u = np.r_[rng.uniform(-3, 3, 2), rng.normal(size=2)], rng.uniform(-25, 25, 2)
    pin.framesForwardKinematics(task.model, task.data, x[:2])
    ee = task.data.oMf[task.tip].translation
    e2 = float(np.sum((ee - task.goal) ** 2))
    assert float(task.f_running_cost(x, u, x)) == pytest.approx(0.01 * 0.5 * (10 * e2 + 0.1 * u @ u), rel=1e-12)
    assert float(task.f_terminal_cost(x, x)) == pytest.approx(0.5 * 10 * e2, rel=1e-12)   # no velocity term


def test_casadi_step_matches_pinocchio():
    task = get_task("double_pendulum")
    rng = np.random.default_rng(3)
    for _ in range(5):
        x, u = rng.normal(size=4) * [2, 2, 5, 5], rng.uniform(-25, 25, 2)
        a = pin.aba(task.model, task.data, x[:2], x[2:], u)
        v_next = x[2:] + task.dt * a
        expected = np.concatenate([x[:2] + task.dt * v_next, v_next])
        np.testing.assert_allclose(task.step(x, u), expected, atol=1e-12)
        np.testing.assert_allclose(np.asarray(task.f_step(x, u)).ravel(), expected, atol=1e-9)


def test_underactuated_variant_maps_its_motor_and_accepts_torque_only():
    acro = PendulumTask(n_links=2, actuated=(1,), name="acrobot-test")
    full = get_task("double_pendulum")
    x = np.array([np.pi - 0.3, 0.2, 0.0, 0.0])
    np.testing.assert_allclose(acro.step(x, np.array([2.0])), full.step(x, np.array([0.0, 2.0])), atol=1e-14)
    assert acro.accepted_actions == ("u",) and acro.params()["actuated"] == [1]


def test_bad_actuation_is_refused():
    with pytest.raises(SdpError, match="actuated must list distinct joint indices"):
        PendulumTask(n_links=2, actuated=(2,))
    with pytest.raises(SdpError, match="actuated must list"):
        PendulumTask(n_links=1, actuated=(1,))

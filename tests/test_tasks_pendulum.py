"""Pendulum tasks: the underactuated double pendulums (pendubot, acrobot) against Pinocchio."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.pendulum import PendulumTask

UNDER = {"double_pendulum-pendubot": 0, "double_pendulum-acrobot": 1}


@pytest.mark.parametrize("name", list(UNDER))
def test_one_motor_and_the_casadi_step_matches_pinocchio(name):
    task, j = get_task(name), UNDER[name]
    assert task.nu == 1 and task.nv == 2 and task.u_ub.tolist() == [25.0]
    assert task.params()["actuated"] == [j]
    rng = np.random.default_rng(3)
    for _ in range(5):
        x, u = rng.normal(size=4) * [2, 2, 5, 5], rng.uniform(-25, 25, 1)
        tau = np.zeros(2)
        tau[j] = u[0]
        np.testing.assert_allclose(task.control_to_tau(u), tau)
        a = pin.aba(task.model, task.data, x[:2], x[2:], tau)
        v_next = x[2:] + task.dt * a
        expected = np.concatenate([x[:2] + task.dt * v_next, v_next])
        np.testing.assert_allclose(task.step(x, u), expected, atol=1e-12)
        np.testing.assert_allclose(np.asarray(task.f_step(x, u)).ravel(), expected, atol=1e-9)
    X, U = task.naive_guess(task.sample_xi(rng))
    assert X.shape == (101, 4) and U.shape == (100, 1)


def test_the_unactuated_joint_is_passive():
    """With the motor off, the acrobot and the fully actuated pendulum with tau = 0 agree;
    with the motor on, only joint 2 of the acrobot feels it."""
    full, acro = get_task("double_pendulum"), get_task("double_pendulum-acrobot")
    x = np.array([np.pi - 0.3, 0.2, 0.0, 0.0])
    np.testing.assert_allclose(acro.step(x, np.zeros(1)), full.step(x, np.zeros(2)), atol=1e-14)
    np.testing.assert_allclose(acro.step(x, np.array([2.0])), full.step(x, np.array([0.0, 2.0])), atol=1e-14)
    # fully actuated artifacts keep their recorded task parameters (no "actuated" key)
    assert "actuated" not in full.params()


def test_bad_actuation_is_refused():
    with pytest.raises(SdpError, match="actuated must list distinct joint indices"):
        PendulumTask(n_links=2, actuated=(2,))
    with pytest.raises(SdpError, match="actuated must list"):
        PendulumTask(n_links=1, actuated=(1,))

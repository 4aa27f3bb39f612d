"""The casadi translation of Pinocchio (sdp_cli.dynamics.casadi_model) against Pinocchio itself.

aba, rnea, frame kinematics and integrate on random states, for the pendulum task models and the
raw UR5 and hector (free-flyer) models; every task's casadi step against its Pinocchio step.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from sdp_cli.dynamics.casadi_model import CasadiModel
from sdp_cli.tasks import get_task, task_names
from sdp_cli.tasks.robots import URDFS, load_model

TOL = 1e-9


def _model(name: str) -> pin.Model:
    return get_task(name).model if name in ("pendulum", "double_pendulum") else load_model(name)


def _random_q(model: pin.Model, rng: np.random.Generator) -> np.ndarray:
    """Random configuration; free-flyer: random position and unit quaternion."""
    lo = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -2.0)
    hi = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, 2.0)
    lo, hi = np.maximum(lo, -4.0), np.minimum(hi, 4.0)
    q = pin.randomConfiguration(model, lo, hi)
    for j in model.joints[1:]:
        if j.shortname() == "JointModelFreeFlyer":
            quat = rng.normal(size=4)
            q[j.idx_q + 3:j.idx_q + 7] = quat / np.linalg.norm(quat)
    return q


def _functions(model: pin.Model):
    cm = CasadiModel(model)
    q, v, a, dv = (ca.SX.sym(n, k) for n, k in (("q", model.nq), ("v", model.nv), ("a", model.nv), ("dv", model.nv)))
    frames = [cm.frame_placement(q, f) for f in range(model.nframes)]
    return {
        "aba": ca.Function("aba", [q, v, a], [cm.aba(q, v, a)]),
        "rnea": ca.Function("rnea", [q, v, a], [cm.rnea(q, v, a)]),
        "fk": ca.Function("fk", [q], [ca.horzcat(*[ca.horzcat(R, p) for R, p in frames])]),
        "integrate": ca.Function("integrate", [q, dv], [cm.integrate(q, dv)]),
    }


MODELS = ["pendulum", "double_pendulum", "ur5", "hector"]


def test_all_robots_load():
    assert set(URDFS) == {"double_pendulum", "ur5", "hector"}
    dims = {name: (load_model(name).nq, load_model(name).nv) for name in URDFS}
    assert dims == {"double_pendulum": (2, 2), "ur5": (6, 6), "hector": (7, 6)}
    assert load_model("hector").joints[1].shortname() == "JointModelFreeFlyer"


@pytest.mark.parametrize("name", MODELS)
def test_casadi_matches_pinocchio(name):
    model = _model(name)
    data = model.createData()
    f = _functions(model)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = _random_q(model, rng)
        v, tau, a = (rng.normal(size=model.nv) * s for s in (2.0, 3.0, 5.0))
        ddq = pin.aba(model, data, q, v, tau)
        np.testing.assert_allclose(np.asarray(f["aba"](q, v, tau)).ravel(), ddq, rtol=TOL, atol=TOL * (1 + np.abs(ddq).max()))
        tau_id = pin.rnea(model, data, q, v, a)
        np.testing.assert_allclose(np.asarray(f["rnea"](q, v, a)).ravel(), tau_id, rtol=TOL,
                                   atol=TOL * (1 + np.abs(tau_id).max()))
        pin.framesForwardKinematics(model, data, q)
        fk = np.asarray(f["fk"](q)).reshape(3, model.nframes, 4)
        for k in range(model.nframes):
            M = data.oMf[k]
            np.testing.assert_allclose(fk[:, k, :3], M.rotation, atol=TOL)
            np.testing.assert_allclose(fk[:, k, 3], M.translation, atol=TOL)
        dv = rng.normal(size=model.nv)
        np.testing.assert_allclose(np.asarray(f["integrate"](q, dv)).ravel(), pin.integrate(model, q, dv), atol=TOL)
        # ABA inverts RNEA (a non-trivial round trip through both translations)
        np.testing.assert_allclose(np.asarray(f["aba"](q, v, f["rnea"](q, v, a))).ravel(), a, atol=1e-7)


def test_free_flyer_integrate_small_rotation_branch():
    """exp6 near zero rotation (the Taylor branch) matches Pinocchio."""
    model = load_model("hector")
    f = _functions(model)
    rng = np.random.default_rng(1)
    q = _random_q(model, rng)
    for scale in (1e-9, 1e-5, 1e-3):
        dv = rng.normal(size=6) * scale
        np.testing.assert_allclose(np.asarray(f["integrate"](q, dv)).ravel(), pin.integrate(model, q, dv),
                                   atol=1e-13)


@pytest.mark.parametrize("name", task_names())
def test_f_step_equals_task_step(name):
    task = get_task(name)
    rng = np.random.default_rng(2)
    for _ in range(3):
        xi = task.sample_xi(rng)
        X, U = task.naive_guess(xi)
        t = int(rng.integers(len(U)))
        x = X[t].copy()
        x[task.nq:] += rng.normal(size=task.nv) * 0.5
        u = np.clip(U[t] + rng.normal(size=task.nu), task.u_lb, task.u_ub)
        np.testing.assert_allclose(np.asarray(task.f_step(x, u)).ravel(), task.step(x, u), atol=1e-9)

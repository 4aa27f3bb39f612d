"""UR5 reach tasks: registry names, distribution P, casadi vs Pinocchio, policy maps (finite differences),
inverse dynamics round trip, naive guess."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task, task_descriptions
from sdp_cli.tasks.ur5 import INIT_SPREAD, P_FIXED, Q_HOME, TGT_MAX_REACH, TGT_MIN_R, TGT_MIN_Z, VARIANTS, Ur5Task

NAMES = list(VARIANTS)


@pytest.fixture(scope="module", params=NAMES)
def task(request):
    return get_task(request.param)


def _rngs(n, seed=0):
    return [np.random.default_rng([seed, i]) for i in range(n)]


def test_variants_registered_with_their_booleans():
    desc = task_descriptions()
    for name, (r_init, r_tgt) in VARIANTS.items():
        assert f"r_init={int(r_init)}, r_tgt={int(r_tgt)}" in desc[name]
        t = get_task(name)
        assert (t.name, t.r_init, t.r_tgt) == (name, r_init, r_tgt)
        assert (t.nq, t.nv, t.nx, t.ndx, t.nu, t.n_xi) == (6, 6, 12, 12, 6, 15)
        assert t.T >= 192
    assert get_task("ur5-fixed", T=100).T == 100
    with pytest.raises(SdpError):
        get_task("ur5-fixed", T=1)


def test_torque_limits_are_the_model_effort_limits(task):
    np.testing.assert_array_equal(task.u_ub, [150, 150, 150, 28, 28, 28])
    np.testing.assert_array_equal(task.u_lb, -task.u_ub)
    assert task.n_h == 0


def test_distribution(task):
    xis = np.array([task.sample_xi(r) for r in _rngs(200)])
    q0, v0, tgt = xis[:, :6], xis[:, 6:12], xis[:, 12:]
    assert np.all(v0 == 0)
    if task.r_init:
        assert np.all(np.abs(q0) <= np.pi) and np.ptp(q0, axis=0).min() > 5.0
    else:
        assert np.all(np.abs(q0 - Q_HOME) <= INIT_SPREAD)
    if task.r_tgt:
        assert np.all(tgt[:, 2] >= TGT_MIN_Z) and np.all(np.hypot(tgt[:, 0], tgt[:, 1]) >= TGT_MIN_R)
        # within the arm's reach, away from the stretched-arm singularity (shoulder at (0, 0, 0.089159))
        assert np.all(np.linalg.norm(tgt - [0, 0, 0.089159], axis=1) <= TGT_MAX_REACH)
        assert np.ptp(tgt, axis=0).min() > 0.5
    else:
        assert np.all(tgt == P_FIXED)
    np.testing.assert_array_equal(task.initial_state(xis[0]), xis[0, :12])
    np.testing.assert_array_equal(task.sample_xi(np.random.default_rng(5)),
                                  task.sample_xi(np.random.default_rng(5)))


def test_random_targets_are_reachable_by_ik():
    task = get_task("ur5-rinit-rtgt")
    for r in _rngs(5):
        xi = task.sample_xi(r)
        q = task.inverse_kinematics(task.initial_state(xi)[:6], task.target(xi), iters=500)
        assert np.linalg.norm(task.ee_position_np(q) - task.target(xi)) < 1e-3


def test_casadi_step_and_costs_match_pinocchio():
    task = get_task("ur5-rinit-rtgt")
    rng = np.random.default_rng(1)
    xs, us, xis = ca.SX.sym("x", task.nx), ca.SX.sym("u", task.nu), ca.SX.sym("xi", task.n_xi)
    residuals = ca.Function("r", [xs, us, xis], [task._running_residual(xs, us, xis), task._terminal_residual(xs, xis)])
    for _ in range(5):
        xi = task.sample_xi(rng)
        x = np.concatenate([rng.uniform(-np.pi, np.pi, 6), rng.normal(size=6)])
        u = rng.uniform(task.u_lb, task.u_ub)
        np.testing.assert_allclose(np.asarray(task.f_step(x, u)).ravel(), task.step(x, u), atol=1e-10)
        e = task.ee_position_np(x[:6]) - task.target(xi)
        # results version 2: aligator ur5_reach.py's weights plus a running reach term (300), the velocity
        # weight 0.3 and u regularized around Pinocchio's gravity torques; the tool twist from Pinocchio
        g = pin.computeGeneralizedGravity(task.model, task.data, x[:6])
        pin.forwardKinematics(task.model, task.data, x[:6], x[6:])
        pin.updateFramePlacements(task.model, task.data)
        tw = pin.getFrameVelocity(task.model, task.data, task.ee, pin.LOCAL_WORLD_ALIGNED).vector
        np.testing.assert_allclose(float(task.f_running_cost(x, u, xi)),
                                   0.01 * 0.5 * (1e-4 * x[:6] @ x[:6] + 0.3 * x[6:] @ x[6:] + 1e-4 * (u - g) @ (u - g)
                                                 + 300 * e @ e), rtol=1e-10)
        np.testing.assert_allclose(float(task.f_terminal_cost(x, xi)),
                                   0.5 * (100 * e @ e + 100 * tw @ tw + 1e-4 * x @ x), rtol=1e-10)
        np.testing.assert_allclose(np.asarray(ca.evalf(task.ee_position(ca.DM(x[:6])))).ravel(),
                                   task.ee_position_np(x[:6]), atol=1e-12)
        # the residuals box-FDDP's Gauss-Newton model uses are those of the same costs: l = 1/2 |r|^2
        r = np.asarray(residuals(x, u, xi)[0]).ravel()
        r_T = np.asarray(residuals(x, u, xi)[1]).ravel()
        np.testing.assert_allclose(0.5 * r @ r, float(task.f_running_cost(x, u, xi)), rtol=1e-12)
        np.testing.assert_allclose(0.5 * r_T @ r_T, float(task.f_terminal_cost(x, xi)), rtol=1e-12)


def test_observation_map_and_jacobian_by_finite_differences():
    task = get_task("ur5-fixed")
    rng = np.random.default_rng(2)
    X = np.concatenate([rng.uniform(-4, 4, (3, 6)), rng.normal(size=(3, 6))], axis=1)
    O = task.observation(X)
    assert O.shape == (3, task.n_obs) == (3, 18)
    np.testing.assert_allclose(O[:, :6] ** 2 + O[:, 6:12] ** 2, 1.0)
    J = task.observation_jacobian(X)
    assert J.shape == (3, 18, 12)
    eps = 1e-6
    for b in range(3):
        Jfd = np.stack([(task.observation(task.integrate(X[b], eps * e))
                         - task.observation(task.integrate(X[b], -eps * e))) / (2 * eps)
                        for e in np.eye(12)], axis=1)
        np.testing.assert_allclose(J[b], Jfd, atol=1e-8)
    # state control: the action is x itself
    assert task.action == "x" and task.n_action == 12
    np.testing.assert_array_equal(task.state_action(X), X)
    np.testing.assert_array_equal(task.state_action_jacobian(X)[0], np.eye(12))


def test_inverse_dynamics_inverts_the_step():
    task = get_task("ur5-rinit")
    rng = np.random.default_rng(3)
    X = np.concatenate([rng.uniform(-np.pi, np.pi, (4, 6)), rng.normal(size=(4, 6))], axis=1)
    U = rng.uniform(task.u_lb, task.u_ub, (4, 6))
    Xn = np.array([task.step(x, u) for x, u in zip(X, U)])
    np.testing.assert_allclose(task.inverse_dynamics(X, Xn), U, atol=1e-8)
    np.testing.assert_allclose(task.inverse_dynamics(X[0], Xn[0]), U[0], atol=1e-8)
    # an unreachable (too violent) next state is clipped to the torque limits
    big = X[0].copy()
    big[6:] += 100.0
    u = task.inverse_dynamics(X[0], big)
    assert np.all(u <= task.u_ub) and np.all(u >= task.u_lb)


def test_naive_guess_interpolates_to_an_ik_solution(task):
    xi = task.sample_xi(np.random.default_rng(4))
    X, U = task.naive_guess(xi)
    assert X.shape == (task.T + 1, 12) and U.shape == (task.T, 6)
    np.testing.assert_array_equal(X[0], task.initial_state(xi))
    assert np.linalg.norm(task.ee_position_np(X[-1, :6]) - task.target(xi)) < 1e-2
    assert np.all(U <= task.u_ub) and np.all(U >= task.u_lb)
    assert np.isfinite(task.cost(X, U, xi)) and task.constraint_violation(X, U, xi) == 0.0


def test_ee_frame_is_tool0():
    task = Ur5Task()
    assert task.model.frames[task.ee].name == "tool0"
    pin.framesForwardKinematics(task.model, task.data, Q_HOME)
    np.testing.assert_allclose(task.ee_position_np(Q_HOME), task.data.oMf[task.ee].translation)


# ----------------------------------------------------------------------------- optimizer + gains
def test_solution_and_gains_match_finite_differences():
    """Short-horizon UR5 solve: reaches the target; K_t equals du_t/dx_t of the re-solved tail (FD)."""
    from sdp_cli.trajopt import get_solver
    from sdp_cli.trajopt.verify import check_dynamics_jacobians, check_gains

    task = get_task("ur5-fixed", T=20)
    xi = task.sample_xi(np.random.default_rng(0))
    res = get_solver(task, solver="ipopt", tol=1e-10, jit=False).solve(xi, *task.naive_guess(xi))
    assert res.converged, res.status
    assert res.cost == pytest.approx(task.cost(res.X, res.U, xi), rel=1e-9)
    gaps = [task.difference(task.step(res.X[t], res.U[t]), res.X[t + 1]) for t in range(task.T)]
    assert np.abs(gaps).max() < 1e-8
    assert task.goal_distance(res.X[-1], xi) < task.goal_distance(res.X[0], xi) / 2
    free = [t for t in (0, 6, 12) if not res.clamped[t].any()]   # (the 0.2 s reach saturates some steps)
    assert len(free) >= 2
    errA, errB = check_dynamics_jacobians(task, res, [0, 10])
    assert errA < 1e-6 and errB < 1e-6
    checks = check_gains(task, res, free[:2], eps=1e-5)
    for c in checks:
        assert c.converged and c.rel_error < 1e-4, (c.t, c.rel_error)
        assert np.linalg.norm(c.du_K) > 1e-4  # a non-trivial direction


def test_variants_share_one_compiled_problem():
    """The 4 variants differ only in how xi is sampled: their generated C code is the same, so
    the JIT cache (keyed by the code) compiles the UR5 OCP once, not once per variant."""
    import hashlib
    import os
    import tempfile

    from sdp_cli.trajopt import gains
    from sdp_cli.trajopt.ocp import build_nlp, nlp_functions, stage_blocks
    from sdp_cli.trajopt.solver import compile_tag

    assert len({compile_tag(get_task(name), 200, "fatrop") for name in NAMES}) == 1
    assert compile_tag(get_task("quadrotor-1"), 150, "fatrop") != compile_tag(get_task("quadrotor-3"), 150, "fatrop")
    digests = set()
    for name in ("ur5-fixed", "ur5-rinit-rtgt"):
        task, T = get_task(name), 4
        nlp, layout = build_nlp(task, T)
        blocks = stage_blocks(task)
        gen = ca.CodeGenerator("ocp.c", {"with_header": False})
        for f in nlp_functions(task, nlp, layout, "fatrop", blocks) + [gains.chart_function(task).map(T + 1)]:
            gen.add(f)
        with tempfile.TemporaryDirectory() as tmp:
            gen.generate(tmp + os.sep)
            with open(os.path.join(tmp, "ocp.c"), "rb") as f:
                digests.add(hashlib.sha256(f.read()).hexdigest())
    assert len(digests) == 1

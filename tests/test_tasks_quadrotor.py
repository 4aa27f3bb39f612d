"""Quadrotor tasks: rotor geometry, casadi vs Pinocchio step, constraints, samples outside obstacles,
tangent maps (finite differences), thrust allocation round trip, bounded least squares (KKT)."""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from sdp_cli.tasks import get_task, task_names
from sdp_cli.tasks.quadrotor import (ALLOC, ARM, C_TAU, CLEARANCE, COLUMNS, GOAL_X, R_QUAD, START_X, U_MAX,
                                     Y_RANGE, Z_CEIL, Z_FLOOR, Z_RANGE, bounded_least_squares)

NAMES = [f"quadrotor-{n}" for n in COLUMNS]


def _rand_state(task, rng):
    q = pin.randomConfiguration(task.model, -3 * np.ones(7), 3 * np.ones(7))
    return np.concatenate([q, rng.normal(size=6)])


def test_names_and_dimensions():
    assert set(NAMES + ["quadrotor"]) <= set(task_names())
    for name in NAMES + ["quadrotor"]:
        t = get_task(name)
        assert (t.nq, t.nv, t.nx, t.ndx, t.nu, t.n_xi) == (7, 6, 13, 12, 4, 16)
        assert t.n_h == 2 + len(t.columns)
    assert get_task("quadrotor").name == "quadrotor" and len(get_task("quadrotor").columns) == 0
    assert [len(get_task(n).columns) for n in NAMES] == [0, 1, 3, 9]


def test_allocation_matches_rotor_geometry():
    """Each rotor at ARM along +x, +y, -x, -y pushes along body z; yaw drag alternates."""
    pos = ARM * np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=float)
    spin = np.array([-1, 1, -1, 1])
    for i in range(4):
        f = np.array([0.0, 0.0, 1.0])
        wrench = np.concatenate([f, np.cross(pos[i], f) + spin[i] * C_TAU * f])
        np.testing.assert_allclose(ALLOC[:, i], wrench, atol=1e-15)
    assert np.linalg.matrix_rank(ALLOC) == 4


def test_hover_thrust_holds_the_quadrotor_still():
    task = get_task("quadrotor-0")
    x = np.concatenate([[0.3, -0.2, 1.0, 0, 0, 0, 1], np.zeros(6)])
    np.testing.assert_allclose(task.step(x, task.u_hover), x, atol=1e-12)
    assert np.isclose(task.u_hover.sum(), 1.477 * 9.81) and np.all(task.u_hover < U_MAX)
    up = task.step(x, task.u_hover + 1.0)
    assert up[2] > x[2] and up[9] > 0  # more thrust climbs


def test_casadi_step_matches_pinocchio():
    task = get_task("quadrotor-3")
    rng = np.random.default_rng(0)
    for _ in range(10):
        x, u = _rand_state(task, rng), rng.uniform(task.u_lb, task.u_ub)
        np.testing.assert_allclose(np.asarray(task.f_step(x, u)).ravel(), task.step(x, u), atol=1e-12)
        np.testing.assert_allclose(np.asarray(ca.evalf(task._control_to_tau(ca.DM(u)))).ravel(),
                                   task.control_to_tau(u), atol=1e-15)


def test_gains_of_the_version_2_task_match_finite_differences():
    """The default quadrotor-0 (with the arrival term), full horizon: K_t vs FD of re-solved tails at free steps."""
    from sdp_cli.trajopt import get_solver
    from sdp_cli.trajopt.verify import check_gains

    task = get_task("quadrotor-0")
    xi = task.sample_xi(np.random.default_rng(0))
    res = get_solver(task, solver="ipopt", tol=1e-10, jit=False).solve(xi, *task.naive_guess(xi))
    assert res.converged, res.status
    free = np.flatnonzero(~res.clamped.any(1))
    assert len(free) >= 3
    for c in check_gains(task, res, [int(free[0]), int(free[len(free) // 2]), int(free[-1])], eps=1e-5):
        assert c.converged and c.rel_error < 1e-3, (c.t, c.rel_error)


def test_costs_match_their_formula():
    task = get_task("quadrotor-0")
    rng = np.random.default_rng(1)
    xi = task.sample_xi(rng)
    x, u = _rand_state(task, rng), rng.uniform(0, U_MAX, 4)
    e, v, rot = x[:3] - task.target(xi), x[7:], x[3:6]
    du = u - task.u_hover
    # aligator's weights: 1/2 r^T W r, running x dt, terminal = 12 x running state weights; r = 2 qv
    state = 0.5 * (0.1 * e @ e + 1e-2 * 4 * rot @ rot + 1e-3 * v @ v)
    np.testing.assert_allclose(float(task.f_running_cost(x, u, xi)), 0.01 * (state + 0.5 * 0.1 * du @ du),
                               rtol=1e-12)
    # results version 2: plus the arrival term 1/2 (100 ||e||^2 + 10 ||v||^2)
    np.testing.assert_allclose(float(task.f_terminal_cost(x, xi)), 12 * state + 0.5 * (100 * e @ e + 10 * v @ v),
                               rtol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_state_constraints_are_floor_ceiling_and_inflated_columns(name):
    task = get_task(name)
    rng = np.random.default_rng(2)
    xi = task.sample_xi(rng)
    for _ in range(200):
        x = np.concatenate([rng.uniform([-3, -2.5, -0.5], [3, 2.5, 3.0]), [0, 0, 0, 1], np.zeros(6)])
        h = np.asarray(task.f_state_constraints(x, xi)).ravel()
        assert h.shape == (task.n_h,)
        np.testing.assert_allclose(h[:2], [Z_FLOOR - x[2], x[2] - Z_CEIL])
        clear = task.clearance(x[:3])
        assert np.array_equal(h[2:] <= 0, clear >= 0)
        R = task.columns[:, 2] + R_QUAD
        np.testing.assert_allclose(h[2:], -clear * (clear + 2 * R) / (2 * R), atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_samples_lie_outside_obstacles_at_equal_height(name):
    task = get_task(name)
    xis = np.array([task.sample_xi(np.random.default_rng([0, i])) for i in range(300)])
    start, goal = xis[:, :3], xis[:, 13:16]
    assert np.all(task.clearance(start) >= CLEARANCE) and np.all(task.clearance(goal) >= CLEARANCE)
    np.testing.assert_array_equal(start[:, 2], goal[:, 2])
    assert np.all((start[:, 2] >= Z_RANGE[0]) & (start[:, 2] <= Z_RANGE[1]))
    assert np.all((Z_FLOOR < start[:, 2]) & (start[:, 2] < Z_CEIL))
    np.testing.assert_array_equal(xis[:, 3:13], np.tile([0, 0, 0, 1] + [0] * 6, (300, 1)))
    left = start[:, 0] < 0
    assert 0.3 < left.mean() < 0.7  # start and goal swapped half of the time
    lo, hi = np.where(left, START_X[0], GOAL_X[0]), np.where(left, START_X[1], GOAL_X[1])
    assert np.all((lo <= start[:, 0]) & (start[:, 0] <= hi))
    assert np.all((Y_RANGE[0] <= start[:, 1]) & (start[:, 1] <= Y_RANGE[1]))
    # the straight line between start and goal (the naive guess) usually crosses a column
    blocked = np.mean([task.constraint_violation(*task.naive_guess(xi), xi) > 0 for xi in xis[:100]])
    assert blocked == 0.0 if not len(task.columns) else blocked > 0.6


def test_naive_guess_is_a_straight_line_at_hover():
    task = get_task("quadrotor-1")
    xi = task.sample_xi(np.random.default_rng(3))
    X, U = task.naive_guess(xi)
    assert X.shape == (task.T + 1, 13) and U.shape == (task.T, 4)
    np.testing.assert_array_equal(X[0], task.initial_state(xi))
    np.testing.assert_allclose(X[-1, :3], task.target(xi))
    np.testing.assert_allclose(np.linalg.norm(X[:, 3:7], axis=1), 1.0)
    np.testing.assert_allclose(U, np.tile(task.u_hover, (task.T, 1)))


def test_tangent_maps_and_jacobians_by_finite_differences():
    task = get_task("quadrotor-0")
    rng = np.random.default_rng(4)
    X = np.array([_rand_state(task, rng) for _ in range(3)])
    A = task.observation(X)
    assert A.shape == (3, 12) and task.n_obs == task.n_action == 12 and task.action == "x"
    np.testing.assert_allclose(task.state_action(X), A)
    for x, a in zip(X, A):
        np.testing.assert_allclose(a[:6], pin.difference(task.model, pin.neutral(task.model), x[:7]))
        back = task.state_from_tangent(a)
        np.testing.assert_allclose(task.difference(back, x), 0.0, atol=1e-10)
    J = task.observation_jacobian(X)
    np.testing.assert_allclose(task.state_action_jacobian(X), J)
    eps = 1e-6
    for b in range(3):
        Jfd = np.stack([(task.observation(task.integrate(X[b], eps * e))
                         - task.observation(task.integrate(X[b], -eps * e))) / (2 * eps)
                        for e in np.eye(12)], axis=1)
        np.testing.assert_allclose(J[b], Jfd, atol=1e-7)


def test_casadi_integrate_matches_pinocchio():
    task = get_task("quadrotor-0")
    rng = np.random.default_rng(5)
    for _ in range(5):
        x, dx = _rand_state(task, rng), rng.normal(size=12)
        np.testing.assert_allclose(np.asarray(task.f_integrate(x, dx)).ravel(), task.integrate(x, dx), atol=1e-12)


def test_inverse_dynamics_reproduces_thrusts_of_reachable_states():
    task = get_task("quadrotor-9")
    rng = np.random.default_rng(6)
    X = np.array([_rand_state(task, rng) for _ in range(6)])
    U = rng.uniform(task.u_lb, task.u_ub, (6, 4))
    U[0] = [0.0, U_MAX, 2.0, 0.0]  # thrusts on their bounds are reachable too
    U[1] = task.u_hover
    Xn = np.array([task.step(x, u) for x, u in zip(X, U)])
    np.testing.assert_allclose(task.inverse_dynamics(X, Xn), U, atol=1e-9)
    np.testing.assert_allclose(task.inverse_dynamics(X[2], Xn[2]), U[2], atol=1e-9)


def test_bounded_least_squares_satisfies_kkt():
    rng = np.random.default_rng(7)
    lb, ub = np.zeros(4), np.full(4, U_MAX)
    B = rng.normal(scale=20.0, size=(50, 6))
    U = bounded_least_squares(ALLOC, B, lb, ub)
    assert U.shape == (50, 4) and np.all(U >= lb) and np.all(U <= ub)
    for u, b in zip(U, B):
        g = ALLOC.T @ (ALLOC @ u - b)
        free = (u > lb + 1e-9) & (u < ub - 1e-9)
        np.testing.assert_allclose(g[free], 0.0, atol=1e-8)
        assert np.all(g[u <= lb + 1e-9] >= -1e-8) and np.all(g[u >= ub - 1e-9] <= 1e-8)
    # it beats random feasible points
    cand = rng.uniform(lb, ub, (2000, 4))
    for u, b in zip(U[:5], B[:5]):
        assert np.sum((ALLOC @ u - b) ** 2) <= np.min(np.sum((cand @ ALLOC.T - b) ** 2, axis=1)) + 1e-9


# ----------------------------------------------------------------------------- optimizer + gains
def _solve(name, T, start_xy, goal_xy, z=1.2, arrival=False):
    """A solve of a hand-made scene. The solver tests' scenes (a free step and a clamped one, a path grazing the
    column) were made on aligator's weights alone (``arrival=False``, results version 1): with the arrival term
    of version 2 the short horizons saturate every thrust and the paths no longer graze the column."""
    from sdp_cli.trajopt import get_solver

    task = get_task(name, T=T, arrival=arrival)
    xi = task.sample_xi(np.random.default_rng(0))
    xi[:3] = [*start_xy, z]
    xi[task.nx:task.nx + 3] = [*goal_xy, z]
    res = get_solver(task, solver="ipopt", tol=1e-10, jit=False).solve(xi, *task.naive_guess(xi))
    assert res.converged, res.status
    return task, xi, res


def test_gains_match_finite_differences_without_obstacles():
    """quadrotor-0: K_t (4, 12) in the tangent space vs FD of the re-solved tail, at free and clamped steps."""
    from sdp_cli.trajopt.verify import check_dynamics_jacobians, check_gains

    task, xi, res = _solve("quadrotor-0", 30, (-0.5, 0.0), (0.5, 0.3))
    assert res.K.shape == (30, 4, 12) and res.A.shape == (30, 12, 12)
    np.testing.assert_allclose(np.linalg.norm(res.X[:, 3:7], axis=1), 1.0, atol=1e-9)
    gaps = [task.difference(task.step(res.X[t], res.U[t]), res.X[t + 1]) for t in range(task.T)]
    assert np.abs(gaps).max() < 1e-8
    free = np.flatnonzero(~res.clamped.any(1))
    clamped = np.flatnonzero(res.clamped.any(1))
    assert len(free) >= 2 and len(clamped) >= 1
    errA, errB = check_dynamics_jacobians(task, res, [int(free[0]), int(clamped[0])])
    assert errA < 1e-6 and errB < 1e-6
    for c in check_gains(task, res, [int(free[0]), int(free[-1]), int(clamped[0])], eps=1e-5):
        assert c.converged and c.rel_error < 1e-4, (c.t, c.rel_error)
        assert c.clamped_fd < 1e-8


def test_gains_with_active_column_constraint_match_finite_differences():
    """quadrotor-1 grazing the column: steps whose next states touch it (treated as equalities)."""
    from sdp_cli.trajopt.verify import check_gains

    task, xi, res = _solve("quadrotor-1", 120, (-1.2, 0.05), (1.2, 0.0))
    h = np.array([np.asarray(task.f_state_constraints(x, xi)).ravel() for x in res.X[1:]])  # h(x_1..x_T)
    assert res.max_violation < 1e-6 and h.max() < 1e-6
    active = np.flatnonzero(h[:, 2] > -1e-6) + 1  # states x_s on the inflated column
    assert len(active)
    # steps t whose control is free and whose next state(s) are active
    steps = [s - 1 for s in active if not res.clamped[s - 1].any()]
    steps += [s - 2 for s in active if s >= 2 and not res.clamped[s - 2].any()]
    steps = sorted(set(steps))[:3]
    assert steps
    for c in check_gains(task, res, steps, eps=1e-6, seed=1):
        assert c.converged and c.rel_error < 1e-2, (c.t, c.rel_error)   # measured 2e-3 on the aligator weights


def test_inverse_dynamics_of_diverged_states_is_nan():
    task = get_task("quadrotor-0")
    x = task.initial_state(task.sample_xi(np.random.default_rng(0)))
    bad = x.copy()
    bad[8] = np.nan
    U = task.inverse_dynamics(np.stack([x, x]), np.stack([bad, task.step(x, task.u_hover)]))
    assert np.all(np.isnan(U[0]))
    np.testing.assert_allclose(U[1], task.u_hover, atol=1e-9)


WEAK_BOUND = Path(__file__).parent / "data" / "quadrotor1_weak_thrust_bound.npz"


def test_weak_thrust_bound_fixture_is_ambiguous_at_the_interior_point():
    """The recorded fatrop iterate (tol 1e-6): its multiplier-vs-slack test calls two thrusts free that
    the exact solution holds at the bound; :func:`gains.ambiguous` flags both, so the polish runs."""
    from sdp_cli.trajopt import gains

    d = np.load(WEAK_BOUND)
    task = get_task(str(d["task"]))
    U, lam = d["U_ip"], d["lam_u_ip"]
    wrong = gains.active_controls(U, task.u_lb, task.u_ub, lam) != d["clamped_exact"]
    assert wrong.sum() == 2
    amb = gains.ambiguous(np.abs(lam), np.minimum(task.u_ub - U, U - task.u_lb))
    assert amb[wrong].all()


def test_weak_thrust_bound_is_polished_to_the_exact_active_set():
    """Default solver (fatrop, tol 1e-6) on the fixture's instance: after the active-set polish the
    clamped set equals the exact one and the gains at the two formerly misclassified steps match
    central differences (without the polish: 23-65% off)."""
    from sdp_cli.trajopt import get_solver
    from sdp_cli.trajopt.verify import check_gains

    d = np.load(WEAK_BOUND)
    task = get_task(str(d["task"]), arrival=False)     # recorded on aligator's weights (results version 1)
    res = get_solver(task, jit=False).solve(d["xi"], *task.naive_guess(d["xi"]))
    assert res.converged and res.polish_iterations > 0, res.status
    np.testing.assert_array_equal(res.clamped, d["clamped_exact"])
    np.testing.assert_allclose(res.K[:12], d["K_exact"], rtol=0, atol=1e-4 * np.abs(d["K_exact"]).max())
    steps = [int(t) for t in np.flatnonzero((d["clamped_exact"] != gains_ip(task, d)).any(1))]
    assert steps == [4, 5]
    for c in check_gains(task, res, steps, eps=1e-6, seed=1):
        assert c.converged and c.rel_error < 1e-2, (c.t, c.rel_error)   # measured 8e-6 and 1e-4


def gains_ip(task, d):
    from sdp_cli.trajopt import gains

    return gains.active_controls(d["U_ip"], task.u_lb, task.u_ub, d["lam_u_ip"])


def test_gains_at_a_grazing_contact_are_a_one_sided_derivative():
    """A path that grazes the column for two steps (h ~ 1e-8, active): there the solution map is not
    differentiable (the tail keeps or releases the contact depending on the side of the perturbation),
    so forward and backward differences differ by 19-56% and central differences fit neither. K is the
    derivative on the branch that keeps the contact: it matches one one-sided difference."""
    from sdp_cli.trajopt import get_solver

    task, xi, res = _solve("quadrotor-1", 180, (-1.5, 0.2), (1.5, -0.1))
    h = np.array([np.asarray(task.f_state_constraints(x, xi)).ravel() for x in res.X[1:]])
    touching = np.flatnonzero(h[:, 2] > -1e-6) + 1
    assert len(touching) and res.active_h[touching - 1, 2].all()
    rng, eps = np.random.default_rng(1), 1e-6
    steps = [s - 2 for s in touching if not res.clamped[s - 2].any()]
    assert steps
    kinks = 0
    for t in steps:
        sub = get_solver(task, horizon=task.T - t, solver="ipopt", tol=1e-10, jit=False)
        d = rng.standard_normal(task.ndx)
        d *= eps / np.linalg.norm(d)
        up = sub.solve_from(task.integrate(res.X[t], d), xi, res.X[t:], res.U[t:], gains=False)
        um = sub.solve_from(task.integrate(res.X[t], -d), xi, res.X[t:], res.U[t:], gains=False)
        assert up.converged and um.converged
        fwd, bwd, kd = (up.U[0] - res.U[t]) / eps, (res.U[t] - um.U[0]) / eps, res.K[t] @ d / eps
        rel = [np.linalg.norm(f - kd) / np.linalg.norm(kd) for f in (fwd, bwd)]
        assert min(rel) < 5e-2, (t, rel)            # measured 6e-4 and 1.8e-2
        kinks += np.linalg.norm(fwd - bwd) / np.linalg.norm(kd) > 0.1
    assert kinks == len(steps)


def test_violations_are_told_apart_by_group_in_the_task_and_the_evaluation():
    """A path through the column breaks ``obstacles`` only, one below the floor ``floor_ceiling`` only; the
    evaluation's per-group rates are the same from a rollout's stored arrays and recomputed from its X."""
    from sdp_cli.algorithm.evaluate import group_violation_rates
    from sdp_cli.algorithm.rollout import evaluate_rollouts

    task = get_task("quadrotor-1")
    assert set(task.state_constraint_groups()) == {"floor_ceiling", "obstacles"}
    assert set(get_task("quadrotor-0").state_constraint_groups()) == {"floor_ceiling"}
    xi = task.sample_xi(np.random.default_rng(3))
    X, U = task.naive_guess(xi)
    through = np.linspace([-1.0, 0.0, 1.0], [1.0, 0.0, 1.0], task.T + 1)       # across the column at (0, 0)
    low = np.linspace([-1.0, 2.0, -0.3], [1.0, 2.0, -0.3], task.T + 1)         # far from it, under the floor
    fine = np.linspace([-1.0, 2.0, 1.0], [1.0, 2.0, 1.0], task.T + 1)
    Xs = np.stack([np.concatenate([p, X[:, 3:]], axis=1) for p in (through, low, fine)])
    Us = np.stack([U, U, U + 10.0])                                            # the third breaks the thrust bound
    by = [task.violations_by_group(Xi, Ui, xi) for Xi, Ui in zip(Xs, Us)]
    assert by[0]["obstacles"] > 0.1 and by[0]["floor_ceiling"] == 0 and by[0]["controls"] == 0
    assert by[1]["floor_ceiling"] == pytest.approx(0.3) and by[1]["obstacles"] == 0
    assert by[2]["controls"] == pytest.approx(U[0, 0] + 10.0 - U_MAX) and by[2]["obstacles"] == by[2]["floor_ceiling"] == 0
    for Xi, Ui, b in zip(Xs, Us, by):
        assert task.constraint_violation(Xi, Ui, xi) == max(b.values())
    xis = np.stack([xi] * 3)
    ev = evaluate_rollouts(task, Xs, Us, xis)
    want = {"controls_violation_rate": 1 / 3, "floor_ceiling_violation_rate": 1 / 3, "obstacles_violation_rate": 1 / 3}
    assert group_violation_rates(ev, {}) == pytest.approx(want)
    older = {"X": Xs, "U": Us, "xi": xis}                                      # a rollout without the group arrays
    assert group_violation_rates(older, {"task": "quadrotor-1"}) == pytest.approx(want)
    # the trajectory figure's words for each rollout and for the whole set
    from sdp_cli.report.figures.traj import _outcome, _shares

    ev["reached"] = np.array([False, False, True])
    assert [_outcome(task, {**ev, **older}, j) for j in range(3)] == [
        "miss, breaks obstacles", "miss, breaks floor_ceiling", "goal, breaks controls"]
    assert _shares(ev, {}) == "goal 33%, breaks controls 33%, breaks floor_ceiling 33%, breaks obstacles 33%"

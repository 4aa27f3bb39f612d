"""Feedback gains K_t = du_t/dx_t of the trajectory optimizer, checked by finite differences.

The key check: perturb x_t of a solved trajectory by +-delta, re-solve the rest of the problem
from t (horizon T - t, warm-started from the tail, tight IPOPT), and compare the change of u_t
with K_t delta (sdp_cli.trajopt.verify). The requirement is a median relative error below 5%
at steps where no control bound is active and at steps where one is; we measure ~1e-7.

The faithful pendulums (|u| <= 25, joint 1 of the
double pendulum needs 29.4 N m to hold its arm horizontal) saturate their motors during the swing-up,
so the same solutions serve the free-step and the clamped-step checks.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from sdp_cli.tasks import get_task
from sdp_cli.trajopt import get_solver
from sdp_cli.trajopt import gains as G
from sdp_cli.trajopt.ocp import stage_blocks
from sdp_cli.trajopt.verify import check_dynamics_jacobians, check_gains

PENDULUMS = ["pendulum", "double_pendulum"]
U_BOUND = 25.0


def _solve(task, seed=0):
    xi = task.sample_xi(np.random.default_rng(seed))
    res = get_solver(task).solve(xi, *task.naive_guess(xi))
    assert res.converged, res.status
    return res


@pytest.fixture(scope="module")
def free_solutions():
    return {name: _solve(get_task(name)) for name in PENDULUMS}


@pytest.fixture(scope="module")
def tight_solutions(free_solutions):
    return {name: (get_task(name), free_solutions[name]) for name in PENDULUMS}


@pytest.mark.parametrize("name", PENDULUMS)
def test_gains_match_finite_differences_at_free_steps(free_solutions, name):
    task, res = get_task(name), free_solutions[name]
    free = np.flatnonzero(~res.clamped.any(1))
    assert len(free) >= 20
    checks = check_gains(task, res, list(free[np.linspace(0, len(free) - 1, 8).round().astype(int)]), eps=1e-4)
    assert all(c.converged for c in checks)
    err = np.array([c.rel_error for c in checks])
    assert np.median(err) < 0.01 and err.max() < 0.05, err
    assert max(np.linalg.norm(c.du_fd) for c in checks) > 1e-6  # the check is not vacuous


@pytest.mark.parametrize("name", ["double_pendulum"])   # the single pendulum swings up unsaturated
def test_gains_match_finite_differences_at_clamped_steps(tight_solutions, name):
    task, res = tight_solutions[name]
    cl = res.clamped
    steps = np.flatnonzero(cl.any(1))
    assert len(steps) >= 3, "the |u| <= 25 swing-up should saturate"
    # U at a clamped control sits on its bound; its gain row is exactly zero
    assert np.allclose(np.abs(res.U[cl]), U_BOUND, atol=1e-5)
    assert np.all(res.K[cl] == 0.0)
    mixed = np.flatnonzero(cl.any(1) & ~cl.all(1))
    if task.nu > 1:
        assert len(mixed) >= 1, "want a step with one clamped and one free control"
    pick = list(mixed[:3]) + [s for s in steps if s not in mixed][:3]
    checks = check_gains(task, res, pick, eps=1e-4)
    assert all(c.converged for c in checks)
    err = np.array([c.rel_error for c in checks])
    assert np.median(err) < 0.05 and err.max() < 0.2, err
    # the clamped controls do not move under the perturbation
    assert max(c.clamped_fd for c in checks) < 1e-8
    # at mixed steps the free control does respond, and K predicts it
    for c in checks:
        if c.clamped.any() and not c.clamped.all():
            assert np.linalg.norm(c.du_fd[~c.clamped]) > 1e-7


@pytest.mark.parametrize("name", PENDULUMS)
def test_dynamics_jacobians_and_closed_loop(free_solutions, tight_solutions, name):
    task = get_task(name)
    for res in (free_solutions[name],):
        errA, errB = check_dynamics_jacobians(task, res, [0, 7, 33, 99])
        assert errA < 1e-6 and errB < 1e-6
        np.testing.assert_allclose(res.Phi, res.A + np.einsum("tij,tjk->tik", res.B, res.K), atol=1e-12)


def test_tangent_space_jacobians_free_flyer():
    """nx != ndx (quaternion): A, B from the tangent-space linearization vs FD of task.step
    (on a simulated trajectory: A maps to the tangent space at x_{t+1} = f(x_t, u_t))."""
    task = get_task("quadrotor-1")
    T = 4
    xi = task.sample_xi(np.random.default_rng(0))
    X, U = task.naive_guess(xi)
    rng = np.random.default_rng(1)
    U = U[:T] + rng.normal(size=(T, task.nu))
    X = task.simulate(task.integrate(X[0], rng.normal(size=task.ndx) * 0.3), U)  # a dynamically feasible X
    jac_f, hess_stage, hess_term, _ = stage_blocks(task)
    funcs = {"jac_f_map": jac_f.map(T), "hess_stage_map": hess_stage.map(T), "hess_term": hess_term,
             "chart_map": G.chart_function(task).map(T + 1)}
    A, B, H, HT, dh = G.linearize(funcs, task, X, U, xi, np.zeros((T, task.nx)), np.zeros((T, task.n_h)))
    assert A.shape == (T, 12, 12) and B.shape == (T, 12, 4) and H.shape == (T, 16, 16) and dh.shape == (T + 1, 3, 12)
    errA, errB = check_dynamics_jacobians(task, SimpleNamespace(X=X, U=U, A=A, B=B), range(T))
    assert errA < 1e-6 and errB < 1e-6


def test_fast_riccati_equals_reference_recursion():
    rng = np.random.default_rng(0)
    T, ndx, nu = 12, 4, 3
    A = np.eye(ndx) + 0.1 * rng.normal(size=(T, ndx, ndx))
    B = rng.normal(size=(T, ndx, nu))
    M = rng.normal(size=(T, ndx + nu, ndx + nu))
    H = M @ M.transpose(0, 2, 1) + 0.1 * np.eye(ndx + nu)
    HT = np.eye(ndx)
    clamped = rng.random((T, nu)) < 0.3
    K_ref, _ = G.riccati_gains(A, B, H, HT, clamped)
    K = G.riccati_gains_fast(G.riccati_function(ndx, nu, T), A, B, H, HT, clamped)
    np.testing.assert_allclose(K, K_ref, atol=1e-10)
    assert np.all(K[clamped] == 0)


def _direct_gain(A, B, H, HT, clamped, C, t):
    """du_t/dx_t of the tail LQ problem from t by one big KKT solve (equality-constrained QP)."""
    T, ndx, nu = B.shape
    nz = (T - t) * (ndx + nu)  # z = (dx_t, du_t, dx_{t+1}, du_{t+1}, ..., dx_T)
    nz = (T - t) * (ndx + nu) + ndx
    ix = lambda s: (s - t) * (ndx + nu)  # noqa: E731
    iu = lambda s: ix(s) + ndx  # noqa: E731
    Q = np.zeros((nz, nz))
    for s in range(t, T):
        Q[ix(s):iu(s) + nu, ix(s):iu(s) + nu] = H[s]
    Q[ix(T):, ix(T):] = HT
    rows = []
    fix = np.zeros((ndx, nz))
    fix[:, ix(t):ix(t) + ndx] = np.eye(ndx)  # dx_t = given
    rows.append(fix)
    for s in range(t, T):
        r = np.zeros((ndx, nz))
        r[:, ix(s + 1):ix(s + 1) + ndx] = np.eye(ndx)
        r[:, ix(s):ix(s) + ndx] = -A[s]
        r[:, iu(s):iu(s) + nu] = -B[s]
        rows.append(r)
        for i in np.flatnonzero(clamped[s]):
            c = np.zeros((1, nz))
            c[0, iu(s) + i] = 1.0
            rows.append(c)
        if C[s + 1].shape[0]:
            c = np.zeros((C[s + 1].shape[0], nz))
            c[:, ix(s + 1):ix(s + 1) + ndx] = C[s + 1]
            rows.append(c)
    E = np.vstack(rows)
    rhs = np.zeros((E.shape[0], ndx))
    rhs[:ndx] = np.eye(ndx)
    KKT = np.block([[Q, E.T], [E, np.zeros((E.shape[0], E.shape[0]))]])
    sol = np.linalg.lstsq(KKT, np.vstack([np.zeros((nz, ndx)), rhs]), rcond=None)[0]
    assert np.allclose(E @ sol[:nz], rhs, atol=1e-8), "tail problem infeasible"
    return sol[iu(t):iu(t) + nu]


def test_state_constrained_riccati_matches_direct_kkt():
    """Active state constraints as equalities: relative degree 1 (pushed onto du directly) and
    relative degree 2 (carried back one stage), with clamped controls, vs a direct KKT solve."""
    rng = np.random.default_rng(3)
    T, ndx, nu, dt = 8, 4, 2, 0.1
    Ac = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    A = np.repeat(Ac[None], T, 0) + 0.01 * rng.normal(size=(T, ndx, ndx))
    B = np.zeros((T, ndx, nu))
    B[:, 2:] = dt * (np.eye(2) + 0.1 * rng.normal(size=(T, 2, 2)))  # u acts on velocities only
    M = rng.normal(size=(T, ndx + nu, ndx + nu))
    H = M @ M.transpose(0, 2, 1) + 0.5 * np.eye(ndx + nu)
    HT = 2 * np.eye(ndx)
    clamped = np.zeros((T, nu), dtype=bool)
    clamped[2, 1] = clamped[6, 0] = True
    C = [np.zeros((0, ndx)) for _ in range(T + 1)]
    C[5] = np.array([[1.0, 0.3, 0.0, 0.0]])  # position constraint: relative degree 2
    C[7] = np.array([[0.0, 0.0, 0.2, 1.0]])  # velocity constraint: relative degree 1
    K, _ = G.riccati_gains(A, B, H, HT, clamped, C)
    for t in [0, 1, 2, 3, 5, 6, 7]:  # t = 4: the position constraint at 5 is not controllable from x_4
        np.testing.assert_allclose(K[t], _direct_gain(A, B, H, HT, clamped, C, t), atol=1e-8, err_msg=f"t={t}")
    assert np.all(K[clamped] == 0)


def test_lagrangian_hessian_matters(free_solutions):
    """Dropping the multiplier terms (cost-only Hessian) gives gains that fail the FD check:
    the check can catch that bug."""
    task, res = get_task("double_pendulum"), free_solutions["double_pendulum"]
    solver = get_solver(task)
    T = task.T
    funcs = solver._gfun
    A, B, H, HT, _ = G.linearize(funcs, task, res.X, res.U, res.xi, np.zeros((T, task.nx)), np.zeros((T, 0)))
    K_cost = G.riccati_gains(A, B, H, HT, res.clamped)[0]
    steps = [0, 3, 8, 15]
    bad = SimpleNamespace(**{**res.__dict__, "K": K_cost})
    err_cost = np.median([c.rel_error for c in check_gains(task, bad, steps)])
    err_full = np.median([c.rel_error for c in check_gains(task, res, steps)])
    assert err_full < 1e-3 < err_cost


@pytest.mark.slow
def test_state_constrained_gains_quadrotor():
    """Quadrotor with a column (nx = 13 != ndx = 12, n_h = 3): gains at the steps around the
    contact with the column (state constraint active) match FD. Small eps: the contact set
    changes for perturbations of ~1e-4."""
    task = get_task("quadrotor-1")
    res = _solve(task)
    act = np.flatnonzero(res.active_h.any(1)) + 1  # res.active_h[t] is about x_{t+1}
    assert len(act), "the seed-0 instance touches the column"
    steps = sorted({int(act[0]) - 2, int(act[0]) - 1, int(act[0]), int(act[-1])})
    checks = check_gains(task, res, steps, eps=1e-6)
    assert all(c.converged for c in checks)
    err = np.array([c.rel_error for c in checks])
    assert np.median(err) < 0.05, err

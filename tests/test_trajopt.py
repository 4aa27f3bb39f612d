"""The casadi trajectory optimizer (sdp_cli.trajopt): transcription, solves, caching, JIT cache."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.trajopt import SOLVERS, build_count, get_solver
from sdp_cli.trajopt import jit as jitmod
from sdp_cli.trajopt.ocp import build_nlp, nlp_functions
from sdp_cli.trajopt.solver import _plugin_options

PENDULUMS = ["pendulum", "double_pendulum"]


def _xi(task, seed=0):
    return task.sample_xi(np.random.default_rng(seed))


@pytest.fixture(scope="module")
def solved():
    """Default-solver solutions of both pendulum tasks from the naive guess (seed 0)."""
    out = {}
    for name in PENDULUMS:
        task = get_task(name)
        xi = _xi(task)
        out[name] = (task, xi, get_solver(task).solve(xi, *task.naive_guess(xi)))
    return out


@pytest.mark.parametrize("name", PENDULUMS)
@pytest.mark.parametrize("solver", SOLVERS)
def test_solution_is_a_feasible_optimum_of_the_task(name, solver):
    task = get_task(name)
    xi = _xi(task)
    res = get_solver(task, solver=solver).solve(xi, *task.naive_guess(xi))
    assert res.converged, res.status
    assert res.status == "converged" and 0 < res.iterations < 1000
    T = task.T
    assert res.X.shape == (T + 1, task.nx) and res.U.shape == (T, task.nu)
    assert res.K.shape == (T, task.nu, task.ndx) and res.Phi.shape == (T, task.ndx, task.ndx)
    assert res.A.shape == (T, task.ndx, task.ndx) and res.B.shape == (T, task.ndx, task.nu)
    # the reported cost is the task's objective J(X, U; xi)
    assert res.cost == pytest.approx(task.cost(res.X, res.U, xi), rel=1e-10, abs=1e-10)
    # x0 and the dynamics with Pinocchio's numerics (not the casadi translation)
    np.testing.assert_allclose(res.X[0], task.initial_state(xi), atol=1e-12)
    gaps = [task.difference(task.step(res.X[t], res.U[t]), res.X[t + 1]) for t in range(T)]
    assert np.abs(gaps).max() < 1e-6
    # bounds, and the reported violation
    assert task.constraint_violation(res.X, res.U, xi) <= 1e-6
    assert res.max_violation <= 1e-6
    # the swing-up actually happens: the tip ends near the goal
    # (from 2N m away; the paper's weak terminal weight leaves optima 0.1-0.35 m short)
    assert np.linalg.norm(np.asarray(task.ee_position(res.X[-1, :task.nq])).ravel() - task.goal) < 0.5 * task.nq
    assert res.solve_time > 0 and res.solver == solver


@pytest.mark.parametrize("name", PENDULUMS)
def test_warm_start_from_solution_converges_fast(solved, name):
    task, xi, res = solved[name]
    solver = get_solver(task)
    warm = solver.solve(xi, res.X, res.U)
    assert warm.converged, warm.status
    assert warm.iterations <= 10 < res.iterations + 10
    assert warm.cost == pytest.approx(res.cost, rel=1e-5)
    np.testing.assert_allclose(warm.U, res.U, atol=1e-3)


def test_solve_from_explicit_x0_and_sub_horizon(solved):
    task, xi, res = solved["double_pendulum"]
    t = 40
    sub = get_solver(task, horizon=task.T - t)
    assert sub.T == task.T - t
    tail = sub.solve_from(res.X[t], xi, res.X[t:], res.U[t:])
    assert tail.converged, tail.status
    # Bellman: the tail of an optimal trajectory is optimal for the tail problem
    np.testing.assert_allclose(tail.U, res.U[t:], atol=1e-4)
    np.testing.assert_allclose(tail.X[0], res.X[t], atol=1e-12)


@pytest.mark.parametrize("solver", SOLVERS)
def test_tiny_max_iter_reports_non_convergence(solver):
    task = get_task("double_pendulum")
    xi = _xi(task, 3)
    res = get_solver(task, solver=solver, max_iter=2).solve(xi, *task.naive_guess(xi))
    assert not res.converged
    assert res.iterations <= 3  # fatrop counts the initial iterate
    assert res.status.startswith("not converged") and solver in res.status
    assert res.X.shape == (task.T + 1, task.nx) and np.isfinite(res.cost)


def test_solver_failure_is_reported_not_raised():
    """A guess that makes the dynamics overflow: the solve fails, solve() does not raise."""
    task = get_task("pendulum")
    xi = _xi(task)
    X, U = task.naive_guess(xi)
    X[1:, task.nq:] = 1e200
    res = get_solver(task).solve(xi, X, U)
    assert not res.converged and res.status.startswith(("not converged", "solver error"))


def test_building_is_cached_and_resolving_does_not_rebuild(solved):
    task, xi, _ = solved["pendulum"]
    s1 = get_solver(task)
    assert get_solver(task) is s1 and get_solver(task, max_iter=1000) is s1
    n = build_count()
    fn = s1._nlpsol
    for seed in range(3):
        x = _xi(task, seed)
        s1.solve(x, *task.naive_guess(x))
    assert build_count() == n and s1._nlpsol is fn
    other = get_solver(task, max_iter=7)
    assert other is not s1 and build_count() == n + 1
    assert get_solver(task, horizon=task.T) is s1


def test_bad_input_raises_sdp_error():
    task = get_task("pendulum")
    solver = get_solver(task)
    xi = _xi(task)
    X, U = task.naive_guess(xi)
    with pytest.raises(SdpError, match="X_init has shape"):
        solver.solve(xi, X[:-1], U)
    with pytest.raises(SdpError, match="U_init has shape"):
        solver.solve(xi, X, U[:, None])
    with pytest.raises(SdpError, match="xi has shape"):
        solver.solve(xi[:1], X, U)
    Xn = X.copy()
    Xn[3, 0] = np.nan
    with pytest.raises(SdpError, match="NaN"):
        solver.solve(xi, Xn, U)
    with pytest.raises(SdpError, match="x0"):
        solver.solve_from(np.zeros(7), xi, X, U)
    with pytest.raises(SdpError, match="unknown solver"):
        get_solver(task, solver="snopt")
    with pytest.raises(SdpError, match="horizon"):
        get_solver(task, horizon=0)


def test_layout_round_trip_and_fatrop_order():
    task = get_task("quadrotor-1")
    _, lay = build_nlp(task, 4)
    rng = np.random.default_rng(0)
    X, U = rng.normal(size=(5, task.nx)), rng.normal(size=(4, task.nu))
    X2, U2 = lay.unpack(lay.pack(X, U))
    np.testing.assert_array_equal(X2, X)
    np.testing.assert_array_equal(U2, U)
    gap, init, h = lay.g_index()
    rows = np.sort(np.concatenate([gap.ravel(), init, h.ravel()]))
    np.testing.assert_array_equal(rows, np.arange(lay.ng))  # every row exactly once
    st = lay.fatrop_structure()
    assert sum(st["ng"]) + sum(st["nx"][1:]) == lay.ng and sum(st["nx"]) + sum(st["nu"]) == lay.nw


@pytest.mark.parametrize("name", ["double_pendulum", "quadrotor-1"])
@pytest.mark.parametrize("solver", SOLVERS)
def test_structured_derivatives_equal_casadi_ad(name, solver):
    """The hand-assembled nlp_jac_g / nlp_hess_l equal casadi's AD of the NLP (values and patterns)."""
    task = get_task(name)
    nlp, lay = build_nlp(task, 4)
    ref = ca.nlpsol("ref", solver, nlp, _plugin_options(solver, lay, 10, 1e-6))
    mine = {f.name(): f for f in nlp_functions(task, nlp, lay, solver)}
    rng = np.random.default_rng(1)
    w, p, lam_g = rng.normal(size=lay.nw), rng.normal(size=task.nx + task.n_xi), rng.normal(size=lay.ng)
    args = {"nlp_jac_g": (w, p), "nlp_hess_l": (w, p, 0.7, lam_g), "nlp_grad": (w, p, 0.7, lam_g),
            "nlp_grad_f": (w, p), "nlp_f": (w, p), "nlp_g": (w, p)}
    for fname, a in args.items():
        r, m = ref.get_function(fname), mine[fname]
        assert r.name_in() == m.name_in() and r.name_out() == m.name_out(), fname
        ro, mo = r(*a), m(*a)
        ro, mo = (ro, mo) if isinstance(ro, (list, tuple)) else ([ro], [mo])
        for x, y in zip(ro, mo):
            assert x.sparsity() == y.sparsity(), fname
            np.testing.assert_allclose(np.asarray(ca.densify(x)), np.asarray(ca.densify(y)), atol=1e-12, rtol=1e-12)


def test_jit_cache_compiles_once_and_falls_back(tmp_path, monkeypatch):
    monkeypatch.setenv("SDP_CACHE_DIR", str(tmp_path))
    x = ca.SX.sym("x", 2)
    f = ca.Function("sdp_test_f", [x], [ca.sin(x) * x[0]])
    lib = jitmod.compile_functions("sdp_test_lib", [f])
    assert lib is not None
    sos = list((tmp_path / "jit").glob("sdp_test_lib_*.so"))
    assert len(sos) == 1
    mtime = sos[0].stat().st_mtime_ns
    lib2 = jitmod.compile_functions("sdp_test_lib", [f])  # same code: reused, not recompiled
    assert list((tmp_path / "jit").glob("*.so")) == sos and sos[0].stat().st_mtime_ns == mtime
    g = ca.external("sdp_test_f", lib2)
    np.testing.assert_allclose(np.asarray(g([0.3, 2.0])).ravel(), np.sin([0.3, 2.0]) * 0.3)
    # a failing compiler: warn and return None (callers fall back to casadi's VM)
    monkeypatch.setenv("CC", "false")
    jitmod._compiler.cache_clear()
    try:
        h = ca.Function("sdp_test_h", [x], [x * 3])
        with pytest.warns(RuntimeWarning, match="compiling casadi functions failed"):
            assert jitmod.compile_functions("sdp_test_other", [h]) is None
    finally:
        monkeypatch.delenv("CC")
        jitmod._compiler.cache_clear()


@pytest.mark.parametrize("name", ["double_pendulum", "quadrotor-1"])
def test_every_optimization_level_computes_the_same_bits(name, tmp_path, monkeypatch):
    """SDP_JIT_OPT=-O0 (the default suite's, tests/conftest.py) and -O2 (the default) libraries of a task's NLP
    functions give bit-identical outputs: the suite's level tests the pipeline's numbers. Fails if a flag that
    contracts or reassociates floating-point operations (-ffast-math, -march=native's FMA) reaches one level."""
    task = get_task(name)
    nlp, lay = build_nlp(task, 6)
    fns = nlp_functions(task, nlp, lay, "fatrop")
    monkeypatch.setenv("SDP_CACHE_DIR", str(tmp_path))
    libs = {}
    for opt in ("-O0", "-O2"):
        monkeypatch.setenv("SDP_JIT_OPT", opt)
        libs[opt] = jitmod.compile_functions(f"sdp_test_levels_{name.replace('-', '_')}", fns)
        assert libs[opt] is not None
    assert len(list((tmp_path / "jit").glob("*.so"))) == 2          # the level is part of the cache key
    rng = np.random.default_rng(3)
    for f in fns:
        ext = {opt: ca.external(f.name(), lib) for opt, lib in libs.items()}
        for _ in range(3):
            args = [rng.normal(scale=2.0, size=f.sparsity_in(i).nnz()) for i in range(f.n_in())]
            args = [ca.DM(f.sparsity_in(i), a) for i, a in enumerate(args)]
            out = {opt: e(*args) for opt, e in ext.items()}
            out = {opt: o if isinstance(o, (list, tuple)) else [o] for opt, o in out.items()}
            for a, b in zip(out["-O0"], out["-O2"]):
                a, b = np.array(a.nonzeros(), float), np.array(b.nonzeros(), float)
                assert a.tobytes() == b.tobytes(), f.name()


def test_an_unknown_optimization_level_is_one_line(monkeypatch):
    monkeypatch.setenv("SDP_JIT_OPT", "-Ofast")
    with pytest.raises(SdpError, match="SDP_JIT_OPT='-Ofast': expected one of -O0, -O1, -O2, -O3"):
        jitmod.opt_level()


def test_unjitted_solver_gives_the_same_solution(solved):
    task, xi, res = solved["pendulum"]
    plain = get_solver(task, jit=False)
    assert not plain.jitted
    r2 = plain.solve(xi, *task.naive_guess(xi))
    assert r2.converged
    np.testing.assert_allclose(r2.U, res.U, atol=1e-6)
    np.testing.assert_allclose(r2.K, res.K, atol=1e-6)


def test_solver_output_is_silent(capfd):
    task = get_task("pendulum")
    xi = _xi(task, 5)
    for solver in SOLVERS:
        get_solver(task, solver=solver).solve(xi, *task.naive_guess(xi))
    out, err = capfd.readouterr()
    assert out == "" and err == ""

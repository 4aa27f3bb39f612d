"""The trajectory optimizer: a cached casadi NLP solver per (task, horizon, options).

``get_solver(task)`` builds the multiple-shooting NLP of :mod:`sdp_cli.trajopt.ocp` once
per process (and its compiled C code once per machine, see :mod:`sdp_cli.trajopt.jit`);
``solver.solve(xi, X_init, U_init)`` only changes numbers. Every solve returns a
:class:`SolveResult` with the trajectory, solver diagnostics and, at the solution, the
tangent-space dynamics Jacobians and the feedback gains of :mod:`sdp_cli.trajopt.gains`.

Solvers: ``fatrop`` (default; structure-exploiting interior point, stage-wise Riccati
linear algebra) and ``ipopt`` (MUMPS). See ``bench/trajopt.py`` for the comparison.

Active-set polish: the gains need the active set of the exact solution, but an interior
point stopped at ``tol`` 1e-6 leaves weakly active bounds undecided (measured on quadrotor-1
with fatrop: thrusts 4.6e-3 N inside their bound with multiplier 4.7e-5, classified free;
gains off by 20-65% at those steps). When any bound or state constraint is ambiguous
(:func:`sdp_cli.trajopt.gains.ambiguous`), the converged solution is polished by a primal-dual
warm-started IPOPT solve at ``POLISH_TOL`` (3-4 iterations), and classification, gains,
trajectory and cost come from the polished point; iterations and ``solve_time`` stay those of
the solve itself (the polish is counted in ``gain_time``).
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from sdp_cli.errors import SdpError
from sdp_cli.trajopt import gains as _gains
from sdp_cli.trajopt.jit import compile_functions, jit_enabled_by_default
from sdp_cli.trajopt.ocp import Layout, build_nlp, nlp_functions, stage_blocks
from sdp_cli.trajopt.timeout import ForkServer, SolveTimeout, solve_timeout

SOLVERS = ("fatrop", "ipopt")
DEFAULT_SOLVER = "fatrop"
DEFAULT_MAX_ITER = 1000
#: largest magnitude of a guess entry the solver is started from
GUESS_MAX = 1e6
#: tolerance and iteration cap of the active-set polish (see the module docstring)
POLISH_TOL = 1e-10
POLISH_MAX_ITER = 50


@dataclass
class SolveResult:
    """Outcome of one solve on horizon T (shapes below; ``ndx`` is the state tangent size).

    ``converged`` is True only if the solver reports success AND the max constraint
    violation is within the solver's ``viol_tol``. Non-converged results are returned
    (never raised); ``status`` says why.
    """

    X: np.ndarray  # (T+1, nx)
    U: np.ndarray  # (T, nu)
    cost: float
    iterations: int
    converged: bool
    solve_time: float  # seconds spent in the NLP solver
    max_violation: float  # gaps, x0, h <= 0 and control bounds
    status: str
    K: np.ndarray  # (T, nu, ndx) du_t / dx_t
    A: np.ndarray  # (T, ndx, ndx) df/dx
    B: np.ndarray  # (T, ndx, nu) df/du
    Phi: np.ndarray  # (T, ndx, ndx) A + B K
    clamped: np.ndarray = field(default=None)  # (T, nu) bool, controls at a bound
    active_h: np.ndarray = field(default=None)  # (T, n_h) bool, active h(x_1..x_T) <= 0
    gain_time: float = 0.0  # seconds spent in the active-set polish, linearizing and Riccati
    polish_iterations: int = 0  # iterations of the active-set polish (0: not polished)
    solver: str = ""
    x0: np.ndarray = field(default=None)  # (nx,)
    xi: np.ndarray = field(default=None)  # (n_xi,)


_BUILDS = 0
#: fatrop's IpSolverReturnFlag, in order (casadi reports only the number)
_FATROP_FLAGS = ("Success", "MaxIterExceeded", "StopAtTinyStep", "StopAtAcceptablePoint", "LocalInfeasibility",
                 "FeasiblePointFound", "DivergingIterates", "ErrorInStepComputation", "InvalidOption",
                 "InternalError", "Unknown")


def build_count() -> int:
    """How many solvers this process has built (a re-solve must not change it)."""
    return _BUILDS


def _plugin_options(name: str, lay: Layout, max_iter: int, tol: float, viol_tol: float = 1e-6,
                    warm: bool = False) -> dict:
    """Solver options: silent, no "acceptable point" early exit (only ``tol`` counts as
    success), unscaled constraint violation at success <= viol_tol / 10 (so that a solver
    success always passes our own ``max_violation <= viol_tol`` check). ``warm`` (ipopt):
    start from the given primal-dual point with a small barrier (the active-set polish)."""
    opts = {"print_time": False, "error_on_fail": False, "show_eval_warnings": False,
            "equality": lay.equality().tolist()}
    common = {"print_level": 0, "max_iter": max_iter, "tol": tol, "acceptable_iter": 0,
              "constr_viol_tol": 0.1 * viol_tol}
    if name == "ipopt":
        opts["ipopt"] = {**common, "sb": "yes"}
        if warm:
            push = {k: 1e-10 for k in ("warm_start_bound_push", "warm_start_bound_frac", "warm_start_mult_bound_push",
                                       "warm_start_slack_bound_push", "warm_start_slack_bound_frac")}
            opts["ipopt"].update({"warm_start_init_point": "yes", "mu_init": 1e-8, **push})
    else:
        opts.update(lay.fatrop_structure())
        opts["fatrop"] = common
    return opts


class TrajOptSolver:
    """Solver of OCP (1) for one task and horizon (build with :func:`get_solver`)."""

    def __init__(self, task, horizon: int, solver: str = DEFAULT_SOLVER, max_iter: int = DEFAULT_MAX_ITER,
                 tol: float = 1e-6, viol_tol: float = 1e-6, jit: bool = True, polish: bool = True):
        global _BUILDS
        t_start = time.perf_counter()
        self.task, self.T, self.solver_name = task, int(horizon), solver
        self.max_iter, self.tol, self.viol_tol = int(max_iter), float(tol), float(viol_tol)
        # an ipopt solve at the polish tolerance is its own polish
        self.polish = bool(polish) and not (solver == "ipopt" and self.tol <= POLISH_TOL)
        nlp, self.layout = build_nlp(task, self.T)
        opts = _plugin_options(solver, self.layout, self.max_iter, self.tol, self.viol_tol)
        blocks = stage_blocks(task)
        jac_f, hess_stage, hess_term, _ = blocks
        gfun = {"jac_f_map": jac_f.map(self.T), "hess_stage_map": hess_stage.map(self.T),
                "hess_term": hess_term, "chart_map": _gains.chart_function(task).map(self.T + 1),
                "riccati": _gains.riccati_function(task.ndx, task.nu, self.T)}
        tag = compile_tag(task, self.T, solver)
        lib = None
        if jit:
            lib = compile_functions(tag, nlp_functions(task, nlp, self.layout, solver, blocks) + list(gfun.values()))
        self._polisher, self._nlp, self._blocks, self._lib, self._jit = None, nlp, blocks, lib, jit
        if lib is not None:
            self._nlpsol = ca.nlpsol(tag, solver, lib, opts)
            self._gfun = {k: ca.external(f.name(), lib) for k, f in gfun.items()}
        else:
            self._nlpsol = ca.nlpsol(tag, solver, nlp, {**opts, "expand": True})
            self._gfun = gfun
        self.jitted = lib is not None
        self._server = ForkServer(self._run_nlp)   # fatrop's calls, under a wall-clock limit
        self._oracle = ca.external("nlp", lib) if lib is not None else \
            ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]]).expand()
        lay = self.layout
        self._xi_, self._ui_ = lay.x_index(), lay.u_index()
        self._gap_i, self._init_i, self._h_i = lay.g_index()
        self._eq = lay.equality()
        self._lbx, self._ubx = np.full(lay.nw, -np.inf), np.full(lay.nw, np.inf)
        self._lbx[self._ui_] = task.u_lb
        self._ubx[self._ui_] = task.u_ub
        self._lbg = np.where(self._eq, 0.0, -np.inf)
        self._ubg = np.zeros(lay.ng)
        self.build_time = time.perf_counter() - t_start
        _BUILDS += 1

    def __repr__(self) -> str:
        return (f"TrajOptSolver(task={self.task.name!r}, T={self.T}, solver={self.solver_name!r}, "
                f"max_iter={self.max_iter}, jit={self.jitted})")

    # ------------------------------------------------------------------ input
    def _array(self, name: str, a, shape: tuple) -> np.ndarray:
        try:
            arr = np.asarray(a, dtype=float)
        except (TypeError, ValueError):
            raise SdpError(f"{name} must be a numeric array of shape {shape}") from None
        if arr.shape != shape:
            raise SdpError(f"{name} has shape {arr.shape}, expected {shape} "
                           f"(task {self.task.name}, horizon {self.T})")
        if not np.all(np.isfinite(arr)):
            raise SdpError(f"{name} contains NaN or inf")
        return arr

    # ------------------------------------------------------------------ solve
    def solve(self, xi, X_init, U_init, *, gains: bool = True) -> SolveResult:
        """Solve from ``x0 = task.initial_state(xi)``; guess X_init (T+1, nx), U_init (T, nu)."""
        xi = self._array("xi", xi, (self.task.n_xi,))
        return self.solve_from(self.task.initial_state(xi), xi, X_init, U_init, gains=gains)

    def solve_from(self, x0, xi, X_init, U_init, *, gains: bool = True) -> SolveResult:
        """Solve from an explicit initial state ``x0 (nx,)``; never raises on non-convergence."""
        task, T = self.task, self.T
        x0 = self._array("x0", x0, (task.nx,))
        xi = self._array("xi", xi, (task.n_xi,))
        X_init = self._array("X_init", X_init, (T + 1, task.nx))
        U_init = self._array("U_init", U_init, (T, task.nu))
        w0 = self.layout.pack(X_init, U_init)
        w0[self._xi_[0]] = x0
        p = np.concatenate([x0, xi])
        t0 = time.perf_counter()
        f0, g0 = (np.asarray(v) for v in self._oracle(w0, p))
        if not (np.all(np.isfinite(f0)) and np.all(np.isfinite(g0))):
            # never start the solver there: fatrop's line search loops forever from a non-finite iterate
            return self._failed(x0, xi, X_init, U_init, "not converged: the initial guess gives a non-finite "
                                "cost or constraint (solver not started)", time.perf_counter() - t0)
        if np.abs(w0).max() > GUESS_MAX:
            # nor from a finite but absurd one (states of 1e7 and more: seen looping for > 25 min)
            return self._failed(x0, xi, X_init, U_init, f"not converged: the initial guess has entries above "
                                f"{GUESS_MAX:.0e} (solver not started)", time.perf_counter() - t0)
        guard = time.perf_counter() - t0    # the guess checks above count in the solve time, as before

        try:   # fatrop has no time limit of its own: run in a forked solver process (trajopt/timeout.py)
            r, stats, elapsed = self._server.call((w0, p), solve_timeout() if self.solver_name == "fatrop" else 0.0)
        except SolveTimeout as e:
            return self._failed(x0, xi, X_init, U_init, f"not converged: {e}", time.perf_counter() - t0)
        except RuntimeError as e:  # evaluation errors: report, never raise
            solve_time = time.perf_counter() - t0
            return self._failed(x0, xi, X_init, U_init, f"solver error: {str(e).splitlines()[-1]}", solve_time)
        solve_time = guard + elapsed
        w = np.asarray(r["x"]).ravel()
        g = np.asarray(r["g"]).ravel()
        X, U = self.layout.unpack(w)
        viol = self._violation(g, U)
        success = bool(stats.get("success", False))
        converged = success and viol <= self.viol_tol and bool(np.all(np.isfinite(w)))
        raw = stats.get("return_status", "?")
        if self.solver_name == "fatrop":
            flag = stats.get("fatrop", {}).get("return_flag", -1)
            raw = _FATROP_FLAGS[flag] if 0 <= flag < len(_FATROP_FLAGS) else f"return flag {flag}"
        if converged:
            status = "converged"
        elif not success:
            status = f"not converged: {self.solver_name} returned {raw} " \
                     f"({stats.get('unified_return_status', '')}) after {stats.get('iter_count', 0)} iterations"
        else:
            status = f"not converged: constraint violation {viol:.2e} > {self.viol_tol:.0e}"
        res = SolveResult(X=X, U=U, cost=float(np.asarray(r["f"]).ravel()[0]), iterations=int(stats.get("iter_count", 0)),
                          converged=converged, solve_time=solve_time, max_violation=viol, status=status,
                          **self._nan_gains(), solver=self.solver_name, x0=x0, xi=xi)
        lam_g, lam_x = np.asarray(r["lam_g"]).ravel(), np.asarray(r["lam_x"]).ravel()
        t_pol = time.perf_counter()
        if gains and converged and self.polish and self._is_ambiguous(U, lam_x, g, lam_g):
            polished = self._polish(p, w, lam_x, lam_g)
            if isinstance(polished, str):
                res.status += f"; active-set polish failed ({polished}), gains from the interior point's own active set"
            else:
                w, g, lam_x, lam_g, cost, res.polish_iterations = polished
                res.X, res.U = self.layout.unpack(w)
                res.cost, res.max_violation = cost, self._violation(g, res.U)
        polish_time = time.perf_counter() - t_pol
        res.clamped = _gains.active_controls(res.U, task.u_lb, task.u_ub, lam_x[self._ui_])
        mu_h = lam_g[self._h_i]
        res.active_h = (mu_h > 0) & (mu_h > -g[self._h_i])  # multiplier exceeds slack, as for u
        if gains and np.all(np.isfinite(w)):
            self._add_gains(res, lam_g)
        res.gain_time += polish_time
        return res

    def _run_nlp(self, w0, p):
        """One solver call (in the solver process): outputs, the stats we read, and its wall time
        (measured where the solver runs: no pipe overhead)."""
        t1 = time.perf_counter()
        out = self._nlpsol(x0=w0, p=p, lbx=self._lbx, ubx=self._ubx, lbg=self._lbg, ubg=self._ubg)
        st = self._nlpsol.stats()
        keep = {k: st.get(k) for k in ("success", "return_status", "unified_return_status", "iter_count")}
        keep["fatrop"] = {"return_flag": (st.get("fatrop") or {}).get("return_flag", -1)}
        return {k: np.asarray(v) for k, v in out.items()}, keep, time.perf_counter() - t1

    # ------------------------------------------------------------------ polish
    def _is_ambiguous(self, U, lam_x, g, lam_g) -> bool:
        """Is any control bound or state constraint undecided at this interior point?"""
        task = self.task
        s_ub, s_lb = task.u_ub - U, U - task.u_lb
        s_u = np.minimum(s_ub, s_lb)
        z_u = np.abs(lam_x[self._ui_].reshape(U.shape))
        return bool(_gains.ambiguous(z_u, s_u).any()
                    or _gains.ambiguous(np.abs(lam_g[self._h_i]), -g[self._h_i]).any())

    def _polish(self, p, w, lam_x, lam_g):
        """Warm-started IPOPT at ``POLISH_TOL`` from a converged primal-dual point.
        Returns ``(w, g, lam_x, lam_g, cost, iterations)``, or the reason it failed (str)."""
        if self._polisher is None:  # built on first use, not counted as a solver build
            lib = self._lib if self.solver_name == "ipopt" else None
            if lib is None and self._jit:  # the fatrop library lacks ipopt's signatures
                lib = compile_functions(compile_tag(self.task, self.T, "ipopt") + "_polish",
                                        nlp_functions(self.task, self._nlp, self.layout, "ipopt", self._blocks))
            opts = _plugin_options("ipopt", self.layout, POLISH_MAX_ITER, POLISH_TOL, self.viol_tol, warm=True)
            name = compile_tag(self.task, self.T, self.solver_name) + "_polish"
            self._polisher = ca.nlpsol(name, "ipopt", lib, opts) if lib is not None else \
                ca.nlpsol(name, "ipopt", self._nlp, {**opts, "expand": True})
        try:
            r = self._polisher(x0=w, lam_x0=lam_x, lam_g0=lam_g, p=p, lbx=self._lbx, ubx=self._ubx,
                               lbg=self._lbg, ubg=self._ubg)
            stats = self._polisher.stats()
        except RuntimeError as e:
            return str(e).splitlines()[-1]
        wp, gp = np.asarray(r["x"]).ravel(), np.asarray(r["g"]).ravel()
        if not (stats.get("success") and np.all(np.isfinite(wp))
                and self._violation(gp, self.layout.unpack(wp)[1]) <= self.viol_tol):
            return f"ipopt returned {stats.get('return_status', '?')}"
        return (wp, gp, np.asarray(r["lam_x"]).ravel(), np.asarray(r["lam_g"]).ravel(), float(r["f"]),
                max(1, int(stats.get("iter_count", 0))))

    def _violation(self, g: np.ndarray, U: np.ndarray) -> float:
        v = np.concatenate([np.abs(g[self._eq]), np.maximum(g[~self._eq], 0.0),
                            np.maximum(U - self.task.u_ub, 0.0).ravel(),
                            np.maximum(self.task.u_lb - U, 0.0).ravel()])
        return float(np.max(v, initial=0.0)) if np.all(np.isfinite(v)) else float("inf")

    def _nan_gains(self) -> dict:
        T, ndx, nu = self.T, self.task.ndx, self.task.nu
        nan = np.full
        return {"K": nan((T, nu, ndx), np.nan), "A": nan((T, ndx, ndx), np.nan),
                "B": nan((T, ndx, nu), np.nan), "Phi": nan((T, ndx, ndx), np.nan)}

    def _failed(self, x0, xi, X, U, status, solve_time) -> SolveResult:
        try:  # violation of the guess, evaluated without the solver
            g = np.asarray(self._oracle(self.layout.pack(X, U), np.concatenate([x0, xi]))[1])
        except RuntimeError:
            g = np.full(self.layout.ng, np.inf)
        return SolveResult(X=X, U=U, cost=float("nan"), iterations=0, converged=False, solve_time=solve_time,
                           max_violation=self._violation(g.ravel(), U), status=status, **self._nan_gains(),
                           clamped=np.zeros((self.T, self.task.nu), dtype=bool),
                           active_h=np.zeros((self.T, self.task.n_h), dtype=bool), solver=self.solver_name,
                           x0=x0, xi=xi)

    def _add_gains(self, res: SolveResult, lam_g: np.ndarray) -> None:
        t0 = time.perf_counter()
        task = self.task
        mu_h = lam_g[self._h_i]
        _gains.set_solution_gains(res, task, self._gfun, self._gfun["riccati"], lam_g[self._gap_i], mu_h)
        res.gain_time = time.perf_counter() - t0


_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
#: solvers kept per task (least recently used dropped first): `bench/trajopt.py`'s gain check builds one
#: per checked step's horizon, and an unbounded cache grew to 17.5 GB
SOLVER_CACHE_SIZE = 8


def compile_tag(task, T: int, solver: str) -> str:
    """Name of the compiled library (and casadi solver) of ``task`` on horizon ``T``.

    Task variants with the same ``compile_family`` share it; the cache key adds the hash
    of the generated code, so a shared name never mixes different problems.
    """
    family = getattr(task, "compile_family", None) or task.name
    return "sdp_" + "".join(c if c.isalnum() else "_" for c in family).strip("_").replace("__", "_") \
        + f"_T{int(T)}_{solver}"


def get_solver(task, horizon: int | None = None, *, solver: str = DEFAULT_SOLVER,
               max_iter: int = DEFAULT_MAX_ITER, tol: float = 1e-6, viol_tol: float = 1e-6,
               jit: bool | None = None) -> TrajOptSolver:
    """The solver of ``task`` on ``horizon`` (default ``task.T``), built once per process.

    ``solver``: ``"fatrop"`` or ``"ipopt"``; ``max_iter``: iteration cap (non-converged
    solves are reported, not kept silently); ``tol``: solver tolerance; ``viol_tol``: max
    constraint violation accepted as converged; ``jit``: compile the NLP functions with gcc
    into the on-disk cache (default on unless ``SDP_JIT=0``; falls back when compiling fails).
    """
    if solver not in SOLVERS:
        raise SdpError(f"unknown solver {solver!r}; valid solvers: {', '.join(SOLVERS)}")
    T = task.T if horizon is None else int(horizon)
    if T < 1:
        raise SdpError(f"horizon must be >= 1, got {horizon}")
    if int(max_iter) < 0:
        raise SdpError(f"max_iter must be >= 0, got {max_iter}")
    if not (tol > 0 and viol_tol > 0):
        raise SdpError("tol and viol_tol must be > 0")
    jit = jit_enabled_by_default() if jit is None else bool(jit)
    key = (T, solver, int(max_iter), float(tol), float(viol_tol), jit)
    per_task = _CACHE.setdefault(task, {})
    if key in per_task:
        per_task[key] = per_task.pop(key)          # most recently used last
    else:
        while len(per_task) >= SOLVER_CACHE_SIZE:  # bounded: the gain check builds one per re-solved horizon
            per_task.pop(next(iter(per_task)))
        per_task[key] = TrajOptSolver(task, T, solver, int(max_iter), float(tol), float(viol_tol), jit)
    return per_task[key]

"""Box-FDDP: the paper's solver family (DDP), batched over instances, on the task's own OCP.

Algorithm (our implementation, read from the papers; no crocoddyl or aligator code):

- **FDDP** (Mastalli et al., "Crocoddyl: an efficient and versatile framework for multi-contact optimal
  control", ICRA 2020): iterates ``(X, U)`` may have dynamics gaps ``fbar_{t+1} = f(x_t, u_t) - x_{t+1}``
  (and ``fbar_0 = x_0 - X_0``). The backward pass is a Riccati recursion of the LQ model with the gaps
  (``V'_x = V_x + V_xx fbar``); the forward pass is the nonlinear rollout
  ``u^_t = clip(u_t + a k_t + K_t (x^_t - x_t))``, ``x^_{t+1} = f(x^_t, u^_t) - (1 - a) fbar_{t+1}``,
  ``x^_0 = X_0 + a fbar_0``: a step ``a = 1`` closes every gap, ``a < 1`` shrinks them by ``1 - a``.
- **Control bounds** in the backward pass by the projected-Newton box QP of Tassa et al., "Control-limited
  differential dynamic programming", ICRA 2014 (:mod:`sdp_cli.trajopt.boxqp`): ``k_t`` solves
  ``min 1/2 du' Quu du + Qu' du`` on ``u_lb - u_t <= du <= u_ub - u_t``, ``K_t`` has zero rows on the clamped
  controls; the rollout clips to the bounds.
- **Hessians**: Gauss-Newton in the dynamics (no second-order dynamics term), as FDDP. The cost Hessians: where
  the task declares its costs as residuals ``l = 1/2 |r|^2`` (:meth:`~sdp_cli.tasks.base.Task._running_residual`:
  UR5), the Gauss-Newton model ``r_z' r_z`` (``hessian="gn"``), as crocoddyl's residual costs give it; otherwise
  the exact Hessians projected onto the positive semi-definite cone (``hessian="psd"``;
  :func:`~sdp_cli.trajopt.ddp_passes._psd_model`). ``"auto"`` (the default) picks the first that applies. The
  exact Hessians of UR5's end-effector costs are indefinite (most iterations were failed factorizations: 95-141
  iterations from the naive guess; 14-48 with the projection; the same optima); ``hessian="exact"`` (before
  2026-12-06) for comparisons.
  The feedback gains stored with a solution are recomputed at the converged point with the exact Hessian of
  the Lagrangian (co-states ``lambda_{t+1} = V_x(t+1)``) by :func:`sdp_cli.trajopt.gains.riccati_gains`, the
  same code that gives fatrop's solutions their gains, so a DDP dataset trains SDP on true sensitivities. They
  are taken after a **polish**: a converged instance (``gains=True``) iterates on to the stopping measure
  ``POLISH_TOL`` (at most ``POLISH_MAX_ITER`` more iterations) and returns its last converged point, since at
  ``STOP_TOL`` its gains are ~1e-4 off the sensitivities (median over t; 1e-6 after the polish,
  ``tests/test_ddp.py`` at the pipeline's settings). ``iterations`` and ``solve_time`` are those to ``tol``; the
  polish is counted in ``gain_time`` and ``polish_iterations``, as fatrop's active-set polish is.
- **Regularization** ``Quu + mu I``: ``mu`` starts at ``REG_INIT``; x10 when the backward pass meets a
  ``Quu + mu I`` that is not positive definite or the accepted step is <= ``STEP_INC`` (or none is accepted);
  /10 (not below ``REG_MIN``) when the step is > ``STEP_DEC``; above ``REG_MAX`` the solve stops, failed.
- **Line search**: steps ``1, 1/2, ..., 2^-10``; the expected change of a step ``a`` is the LQ model's
  ``a d1 + a^2 / 2 d2`` along the full step (``d1``: gradient, ``d2``: curvature, both with the gaps); a step
  is accepted when the actual cost decrease is >= ``ACCEPT`` x the expected one, or, where the model predicts
  an increase (closing gaps can cost), when the increase is at most ``ACCEPT_NEG`` x the predicted one.
- **Stopping rule, "converged"**: the iterate is feasible (every gap <= ``GAP_TOL``) and the squared norm of
  the free part of ``Q_u`` summed over the horizon (the reduced gradient; the measure of crocoddyl's
  ``stoppingCriteria()``, not the ``abs(d1 + d2/2)`` crocoddyl 3.x's solve stops on: docs/trajopt.md) is
  <= ``tol`` (default ``STOP_TOL``); a solve that reaches ``max_iter`` (default 1000) iterations, or
  ``REG_MAX``, is "not converged", its last iterate returned.

Batched: ``solve_batch`` iterates N instances together as arrays ``(N, T, ...)``: derivatives in one call of
a compiled casadi map over ``N T`` stages, the backward pass and the rollouts as array operations over the
instances (sequential in t only). An instance that converged (or failed) leaves the active set and stops
changing. Its ``solve_time`` is its iterations x the batch's wall time per instance-iteration, so the times
of a batch sum to its wall time (recorded as ``batch_wall_time`` on every result).

Every task: a state on a manifold (the quadrotor's SE(3) base) is handled in the tangent space
(:mod:`sdp_cli.trajopt.ddp_model`), state constraints ``h(x) <= 0`` (the quadrotor's floor, ceiling and columns)
by an augmented-Lagrangian outer loop (:mod:`sdp_cli.trajopt.ddp_al`) whose updates happen per instance inside
the same batched iterations; "converged" then also requires every ``h <= H_TOL`` and the iteration count (and
its cap) is that of all inner DDP iterations. The feedback gains of such a solution come from the same code as
fatrop's (:func:`sdp_cli.trajopt.gains.linearize`, active state constraints as equalities), with the ambient
co-states of the adjoint recursion (:func:`~sdp_cli.trajopt.ddp_model.ambient_costates`) and the multipliers
``max(0, lam + rho h)``.
"""

from __future__ import annotations

import time
import weakref

import casadi as ca
import numpy as np

from sdp_cli.errors import SdpError
from sdp_cli.trajopt import ddp_al as al
from sdp_cli.trajopt.ddp_gains import GainsMixin
from sdp_cli.trajopt.ddp_passes import ACCEPT, ACCEPT_NEG, ALPHAS, PassesMixin, _mv, _psd_model  # noqa: F401
from sdp_cli.trajopt.ddp_model import DenseCall
from sdp_cli.trajopt.ddp_model import cols as _cols
from sdp_cli.trajopt.ddp_model import ddp_functions, gauss_newton, general, left_inverse, to_tangent
from sdp_cli.trajopt.jit import compile_functions, jit_enabled_by_default
from sdp_cli.trajopt.solver import DEFAULT_MAX_ITER, SolveResult

STOP_TOL = 1e-9
GAP_TOL = 1e-9
REG_INIT, REG_MIN, REG_MAX, REG_FACTOR = 1e-9, 1e-9, 1e9, 10.0
#: where the stored gains are taken (``gains=True``): a converged instance iterates on to this stopping measure
#: (at most POLISH_MAX_ITER more iterations), since at STOP_TOL its gains are off the sensitivities by ~1e-4
#: (median over t; tests/test_ddp.py checks them against finite differences at the pipeline's settings)
POLISH_TOL, POLISH_MAX_ITER = 1e-13, 30
STEP_INC, STEP_DEC = 0.01, 0.5
#: the stopping measure compared with ``tol``: "ours" (the squared free part of Q_u summed over the horizon,
#: crocoddyl's ``stoppingCriteria()``) or "crocoddyl" (``|d1 + d2/2|`` of the full step, what crocoddyl 3.x's solve
#: stops on): bench/crocoddyl_compare.py compares iterations under one rule with ``--ddp-stop crocoddyl``
STOP_RULES = ("ours", "crocoddyl")
#: the Hessian model of the iterations: "gn" (Gauss-Newton over the task's residuals, ddp_model.gauss_newton),
#: "psd" (the cost Hessians projected onto the PSD cone, ddp_passes._psd_model) or "exact"; "auto": "gn" where the
#: task declares residuals, else "psd". The stored gains use the exact Hessian of the Lagrangian whatever the model
HESSIANS = ("auto", "gn", "psd", "exact")


class DDPSolver(PassesMixin, GainsMixin):
    """Box-FDDP for one task and horizon (see the module docstring); ``solve`` / ``solve_from`` return a
    :class:`~sdp_cli.trajopt.solver.SolveResult` like the NLP solvers, ``solve_batch`` N of them."""

    solver_name = "ddp"

    def __init__(self, task, horizon: int | None = None, max_iter: int = DEFAULT_MAX_ITER, tol: float = STOP_TOL,
                 jit: bool | None = None, hessian: str = "auto", stop_rule: str = "ours"):
        if hessian not in HESSIANS:
            raise SdpError(f"hessian must be one of {', '.join(HESSIANS)}, got {hessian!r}")
        if stop_rule not in STOP_RULES:
            raise SdpError(f"stop_rule must be one of {', '.join(STOP_RULES)}, got {stop_rule!r}")
        if hessian == "auto":
            hessian = "gn" if gauss_newton(task) else "psd"
        elif hessian == "gn" and not gauss_newton(task):
            raise SdpError(f"hessian 'gn' needs a task that declares its costs as residuals; {task.name} does not")
        self.hessian, self.stop_rule = hessian, stop_rule
        self.task, self.T = task, int(task.T if horizon is None else horizon)
        if self.T < 1 or int(max_iter) < 0 or not tol > 0:
            raise SdpError("horizon must be >= 1, max_iter >= 0 and tol > 0")
        self.max_iter, self.tol = int(max_iter), float(tol)
        funcs = ddp_functions(task, self.T, hessian)
        jit = jit_enabled_by_default() if jit is None else bool(jit)
        lib = None
        if jit:
            family = getattr(task, "compile_family", None) or task.name
            lib = compile_functions("sdp_ddp_" + "".join(c if c.isalnum() else "_" for c in family) + f"_T{self.T}",
                                    funcs)
        self._f = {f.name(): (ca.external(f.name(), lib) if lib is not None else f) for f in funcs}
        self.jitted = lib is not None
        self._maps: dict = {}
        self.general, self.ndx = general(task), task.ndx

    def __repr__(self) -> str:
        return f"DDPSolver(task={self.task.name!r}, T={self.T}, max_iter={self.max_iter}, jit={self.jitted})"

    def _map(self, name: str, n: int) -> DenseCall:
        """``self._f[name]`` mapped over ``n`` columns, called with numpy in and out (:class:`DenseCall`)."""
        key = (name, n)
        if key not in self._maps:
            self._maps[key] = DenseCall(self._f[name].map(n, "serial"))
        return self._maps[key]

    # ------------------------------------------------------------------ evaluations (batched)
    def _derivatives(self, X, U, xi, al_state=None):
        """Stage and terminal derivatives along ``X (n, T+1, nx)``, ``U (n, T, nu)`` (tangent-space, with the
        penalty at ``al_state = (lam, rho)`` for a :func:`general` task)."""
        n, T, nx, nu = len(X), self.T, self.task.nx, self.task.nu
        m = n * T
        xs = X[:, :-1].reshape(m, nx).T
        us = U.reshape(m, nu).T
        xis = np.repeat(xi, T, axis=0).T
        f, A, B, l, lx, lu, lxx, luu, lux = self._map("sdp_ddp_stage", m)(xs, us, xis)
        d = {"f": np.asarray(f).T.reshape(n, T, nx), "A": _cols(A, m, nx, nx).reshape(n, T, nx, nx),
             "B": _cols(B, m, nx, nu).reshape(n, T, nx, nu), "l": np.asarray(l).reshape(n, T),
             "lx": np.asarray(lx).T.reshape(n, T, nx), "lu": np.asarray(lu).T.reshape(n, T, nu),
             "lxx": _cols(lxx, m, nx, nx).reshape(n, T, nx, nx), "luu": _cols(luu, m, nu, nu).reshape(n, T, nu, nu),
             "lux": _cols(lux, m, nu, nx).reshape(n, T, nu, nx)}
        lT, lTx, lTxx = self._map("sdp_ddp_term", n)(X[:, -1].T, xi.T)
        d["lT"], d["lTx"], d["lTxx"] = np.asarray(lT).ravel(), np.asarray(lTx).T, _cols(lTxx, n, nx, nx)
        d["J"] = d["cost"] = d["l"].sum(1) + d["lT"]       # J: what the line search compares (with the penalty)
        if self.general:
            self._general_derivatives(d, X, xi, al_state)
        # the stored gains' terminal Hessian: the exact one (the iterations' model is Gauss-Newton's under "gn")
        d["lTxx_exact"] = (_cols(self._map("sdp_ddp_term_exact", n)(X[:, -1].T, xi.T), n, nx, nx)
                           if self.hessian == "gn" else d["lTxx"])
        if self.hessian == "psd":
            _psd_model(d)
        return d

    def _chart(self, X, xi):
        """``J_+ (n, T+1, nx, ndx)``, ``h (n, T+1, n_h)`` and ``dh (n, T+1, n_h, ndx)`` along ``X``."""
        n, T1, nx, ndx, nh = len(X), self.T + 1, self.task.nx, self.ndx, self.task.n_h
        Jp, h, dh = self._map("sdp_ddp_chart", n * T1)(X.reshape(n * T1, nx).T, np.repeat(xi, T1, axis=0).T)
        return (_cols(Jp, n * T1, nx, ndx).reshape(n, T1, nx, ndx), np.asarray(h).T.reshape(n, T1, nh),
                _cols(dh, n * T1, nh, ndx).reshape(n, T1, nh, ndx))

    def _h(self, X, xi):
        """``h (n, m, n_h)`` at the states ``X (n, m, nx)``."""
        n, m = X.shape[:2]
        h = self._map("sdp_ddp_h", n * m)(X.reshape(n * m, -1).T, np.repeat(xi, m, axis=0).T)
        return np.asarray(h).T.reshape(n, m, self.task.n_h)

    def _general_derivatives(self, d, X, xi, al_state):
        """Tangent-space derivatives (:func:`~sdp_cli.trajopt.ddp_model.to_tangent`) and the penalty of the
        state constraints on ``x_1..x_T`` (:mod:`~sdp_cli.trajopt.ddp_al`) at the instances'
        ``al_state = (lam, rho)``; ``d["Jm"]`` and ``d["h"]`` kept for the gaps and the outer updates."""
        Jp, h, dh = self._chart(X, xi)
        Jm = left_inverse(Jp)
        to_tangent(d, Jp, Jm)
        d["Jm"], d["h"] = Jm, h[:, 1:]
        if self.task.n_h:
            lam, rho = al_state
            g, H = al.derivatives(h[:, 1:], dh[:, 1:], lam, rho)
            d["lx"][:, 1:] += g[:, :-1]
            d["lxx"][:, 1:] += H[:, :-1]
            d["lTx"] += g[:, -1]
            d["lTxx"] += H[:, -1]
            d["J"] = d["J"] + al.penalty(h[:, 1:], lam, rho)

    def _rollout(self, X, U, gaps, k, K, alpha, xi, Jm=None, al_state=None):
        """The forward pass of a step ``alpha (n,)`` (one compiled call): ``(X^, U^, cost (n,))``; ``Jm``: the
        left inverses ``J_-`` along ``X`` of a :func:`general` task, ``al_state``: its ``(lam, rho)``."""
        task, T = self.task, self.T
        n, nx, nu, ndx = len(X), task.nx, task.nu, self.ndx
        if Jm is not None:              # tangent gaps and gains: x^_0 on the manifold, ambient gains K_t J_-(x_t)
            x0h = np.array([task.integrate(X[i, 0], alpha[i] * gaps[i, 0]) for i in range(n)])
            K = K @ Jm[:, :-1]
        else:
            x0h = X[:, 0] + alpha[:, None] * gaps[:, 0]
        Kv = K.transpose(0, 1, 3, 2).reshape(n * T, nu * nx).T          # vec(K_t), column-major
        Xn, Un, J = self._map(f"sdp_ddp_roll_T{T}", n)(
            x0h.T, U.reshape(n * T, nu).T, k.reshape(n * T, nu).T, Kv, X[:, :-1].reshape(n * T, nx).T,
            gaps[:, 1:].reshape(n * T, ndx).T, alpha[None], xi.T)
        Xh = np.empty_like(X)
        Xh[:, 0] = x0h
        Xh[:, 1:] = np.asarray(Xn).T.reshape(n, T, nx)
        J = np.asarray(J).ravel()
        if task.n_h:                    # the penalty of the state constraints at the instances' lam, rho
            J = J + al.penalty(self._h(Xh[:, 1:], xi), *al_state)
        return Xh, np.asarray(Un).T.reshape(n, T, nu), J

    # ------------------------------------------------------------------ solve
    def solve(self, xi, X_init, U_init, *, gains: bool = True) -> SolveResult:
        xi = np.asarray(xi, float)
        return self.solve_from(self.task.initial_state(xi), xi, X_init, U_init, gains=gains)

    def solve_from(self, x0, xi, X_init, U_init, *, gains: bool = True) -> SolveResult:
        return self.solve_batch(np.asarray(x0, float)[None], np.asarray(xi, float)[None],
                                np.asarray(X_init, float)[None], np.asarray(U_init, float)[None], gains=gains)[0]

    def solve_batch(self, x0, xi, X_init, U_init, *, gains: bool = True, width: int | None = None) -> list[SolveResult]:
        """Solve N instances together: ``x0 (N, nx)``, ``xi (N, n_xi)``, guesses ``X_init (N, T+1, nx)``,
        ``U_init (N, T, nu)``. ``width``: at most this many instances iterate at once, the next ones (in order)
        joining as others finish, so that a straggler does not iterate alone while instances wait (None: all N
        at once). An instance's result does not depend on ``width`` or on its batch. Never raises on
        non-convergence."""
        task, T, ndx = self.task, self.T, self.ndx
        x0, xi = np.asarray(x0, float), np.asarray(xi, float)
        X, U = np.array(X_init, dtype=float), np.array(U_init, dtype=float)
        N = len(x0)
        if X.shape != (N, T + 1, task.nx) or U.shape != (N, T, task.nu) or xi.shape != (N, task.n_xi):
            raise SdpError(f"guesses of shape {X.shape}, {U.shape}, xi {xi.shape} do not match N = {N}, T = {T}, "
                           f"task {task.name}")
        U = np.clip(U, task.u_lb, task.u_ub)
        t_start = time.perf_counter()
        reg = np.full(N, REG_INIT)
        iters = np.zeros(N, dtype=int)
        converged = np.zeros(N, dtype=bool)
        startable = np.all(np.isfinite(X), axis=(1, 2)) & np.all(np.isfinite(U), axis=(1, 2))
        status = np.array(["" if a else "not converged: non-finite guess (solver not started)" for a in startable],
                          dtype=object)
        if width is not None and int(width) < 1:
            raise SdpError(f"width must be >= 1, got {width}")
        width = N if width is None else int(width)
        waiting = list(np.flatnonzero(startable))        # instances not yet started, in order
        active = np.zeros(N, dtype=bool)
        cost = np.full(N, np.nan)
        # the augmented Lagrangian's state per instance (ddp_al; empty without state constraints)
        lam, rho = np.zeros((N, T, task.n_h)), np.full(N, al.RHO_INIT)
        inner_tol, viol_prev = np.full(N, max(al.INNER_TOL_INIT, self.tol)), np.full(N, np.inf)
        # per instance: V_x and the free controls of its last backward pass (for the gains)
        Vx_keep, free_keep = np.zeros((N, T + 1, ndx)), np.ones((N, T, task.nu), dtype=bool)
        lin_keep = {"A": np.zeros((N, T, ndx, ndx)), "B": np.zeros((N, T, ndx, task.nu)),
                    "lTxx": np.zeros((N, ndx, ndx))}
        # polishing (gains only): a converged instance iterates on to POLISH_TOL, so that its stored gains are the
        # sensitivities of the solution (at the solve's tol they are off by ~1e-4); its last point that was
        # converged (stationary, feasible) is what it returns, its iterations those to ``tol``
        polish = gains and POLISH_TOL < self.tol
        polishing = np.zeros(N, dtype=bool)
        conv_iters = np.zeros(N, dtype=int)
        keep = {"X": X.copy(), "U": U.copy(), "cost": np.full(N, np.nan)}
        # every instance leaves after at most max_iter + POLISH_MAX_ITER + 1 iterations
        for _ in range((self.max_iter + POLISH_MAX_ITER + 1) * max(1, -(-len(waiting) // width))):
            room = width - int(active.sum())
            if room > 0 and waiting:
                active[waiting[:room]] = True
                del waiting[:room]
            idx = np.flatnonzero(active)
            if not len(idx):
                break
            Xa, Ua, xia = X[idx], U[idx], xi[idx]
            d = self._derivatives(Xa, Ua, xia, (lam[idx], rho[idx]))
            amb = np.concatenate([(x0[idx] - Xa[:, 0])[:, None], d["f"] - Xa[:, 1:]], axis=1)
            gaps = _mv(d["Jm"], amb) if self.general else amb       # in the tangent space of x_0..x_T
            cost[idx] = d["cost"]
            bad = ~np.isfinite(d["J"])
            clean = np.where(np.isfinite(gaps), gaps, 0.0)
            k, K, Vx, free, stop, ok = self._backward(d, clean, Ua, reg[idx])
            if self.stop_rule == "crocoddyl":   # crocoddyl 3.x's solve: |d1 + d2 / 2| of the full step's LQ model
                d1, d2 = self._model(d, clean, k, K)
                stop = np.abs(d1 + 0.5 * d2)
            feasible = np.abs(amb).max(axis=(1, 2)) <= GAP_TOL
            stationary = ok & feasible & ~bad
            viol = al.violation(d["h"]) if task.n_h else np.zeros(len(idx))
            at_tol = stationary & (stop <= self.tol) & (viol <= al.H_TOL)    # converged (again, when polishing)
            first = at_tol & ~converged[idx]                               # converged at this iteration
            converged[idx[first]] = True
            status[idx[first]] = "converged"
            conv_iters[idx[first]] = iters[idx[first]]
            # the point the gains are taken at: the last converged one
            if at_tol.any():
                c = idx[at_tol]
                Vx_keep[c], free_keep[c] = Vx[at_tol], free[at_tol]
                keep["X"][c], keep["U"][c], keep["cost"][c] = Xa[at_tol], Ua[at_tol], d["cost"][at_tol]
                for key in ("A", "B"):
                    lin_keep[key][c] = d[key][at_tol]
                lin_keep["lTxx"][c] = d["lTxx_exact"][at_tol]
            if polish:   # converged at tol: polish to POLISH_TOL (within its budget)
                polishing[idx[first]] = True
                pol = polishing[idx]
                done = (at_tol & (stop <= POLISH_TOL)) | (pol & (iters[idx] - conv_iters[idx] >= POLISH_MAX_ITER))
            else:
                pol = polishing[idx]
                done = at_tol
            tol = np.where(pol, POLISH_TOL, self.tol)
            # an augmented-Lagrangian subproblem solved, the constraints not yet met: update lam, rho, inner tol
            solved = stationary & ~done & (stop <= inner_tol[idx]) if task.n_h else np.zeros(len(idx), dtype=bool)
            # an update that changes nothing (no constraint violated, the multipliers already mu) only tightens the
            # inner tolerance and steps in the same iteration: it used to take an iteration without a step (6 of 20
            # on quadrotor-0, whose constraints are inactive); the iterates are the same
            noop = solved & (viol <= al.H_TOL)
            if noop.any():
                noop[noop] = np.all(al.multipliers(d["h"][noop], lam[idx[noop]], rho[idx[noop]]) == lam[idx[noop]],
                                    axis=(1, 2))
            outer = solved & ~noop
            if outer.any():
                o = idx[outer]
                lam[o] = al.multipliers(d["h"][outer], lam[o], rho[o])
                slow = viol[outer] > al.VIOL_DECREASE * viol_prev[o]
                rho[o[slow]] = np.minimum(al.RHO_MAX, rho[o[slow]] * al.RHO_FACTOR)
            if solved.any():          # every solved subproblem, updated or not: the next one's tolerance
                c = idx[solved]
                viol_prev[c] = viol[solved]
                inner_tol[c] = np.maximum(tol[solved], inner_tol[c] * al.INNER_FACTOR)
            out_of_iter = (iters[idx] >= self.max_iter) & ~polishing[idx]
            status[idx[out_of_iter & ~done]] = f"not converged: {self.max_iter} iterations (the cap)"
            status[idx[bad & ~done & ~polishing[idx]]] = "not converged: non-finite cost"
            stopped = done | out_of_iter | bad
            active[idx[stopped]] = False
            go = ~stopped
            iters[idx[go]] += 1
            retry = go & ~ok                                    # Quu not positive definite: more regularization
            reg[idx[retry]] *= REG_FACTOR
            search = go & ok & ~outer                           # (an updated penalty needs new derivatives)
            if search.any():
                s = np.flatnonzero(search)
                acc = self._line_search(X, U, idx[s], xi, d, gaps, k, K, s, (lam, rho))
                dec, inc = idx[s][acc > STEP_DEC], idx[s][acc <= STEP_INC]
                reg[dec] = np.maximum(REG_MIN, reg[dec] / REG_FACTOR)
                reg[inc] *= REG_FACTOR
            over = np.flatnonzero(active & (reg > REG_MAX))
            for i in over:          # (rare: the instances that just failed, or a polish that cannot go on)
                if not polishing[i]:
                    status[i] = f"not converged: regularization above {REG_MAX:g} after {iters[i]} iterations"
                    cost[i] = task.cost(X[i], U[i], xi[i])      # a last tiny step may have moved the iterate
            active[over] = False
        # a polished instance returns its last converged point (the derivatives its gains use were taken there)
        pol_all = np.flatnonzero(polishing)
        X[pol_all], U[pol_all], cost[pol_all] = keep["X"][pol_all], keep["U"][pol_all], keep["cost"][pol_all]
        polish_iters = np.where(polishing, iters - conv_iters, 0)
        iters = np.where(converged, conv_iters, iters)
        wall = time.perf_counter() - t_start
        per_iter = wall / max(1, int(iters.sum() + polish_iters.sum()))
        f = self._step_one(X[:, :-1].reshape(N * T, task.nx), U.reshape(N * T, task.nu)).reshape(N, T, task.nx)
        h = self._h(X[:, 1:], xi) if task.n_h else np.zeros((N, T, 0))
        results = []
        for i in range(N):
            gap = np.concatenate([x0[i] - X[i, 0], (f[i] - X[i, 1:]).ravel(), np.maximum(h[i].ravel(), 0.0)])
            res = SolveResult(X=X[i].copy(), U=U[i].copy(), cost=float(cost[i]), iterations=int(iters[i]),
                              converged=bool(converged[i]), solve_time=float(iters[i] * per_iter),
                              max_violation=float(np.abs(gap).max()) if np.all(np.isfinite(gap)) else float("inf"),
                              status=status[i] or "not converged", K=np.full((T, task.nu, ndx), np.nan),
                              A=np.full((T, ndx, ndx), np.nan), B=np.full((T, ndx, task.nu), np.nan),
                              Phi=np.full((T, ndx, ndx), np.nan), clamped=~free_keep[i],
                              active_h=np.zeros((T, task.n_h), dtype=bool), solver="ddp", x0=x0[i].copy(),
                              xi=xi[i].copy())
            res.batch_wall_time = wall
            res.polish_iterations = int(polish_iters[i])
            if gains and converged[i]:
                if self.general:
                    self._add_general_gains(res, al.multipliers(h[i:i + 1], lam[i:i + 1], rho[i:i + 1])[0])
                else:
                    self._add_gains(res, Vx_keep[i], {key: v[i] for key, v in lin_keep.items()})
                res.gain_time += polish_iters[i] * per_iter   # the polish is for the gains: their time, not the solve's
            results.append(res)
        return results

    def _step_one(self, X, U) -> np.ndarray:
        return np.asarray(self._map("sdp_ddp_step", len(X))(X.T, U.T)).T

_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def get_ddp_solver(task, horizon: int | None = None, max_iter: int = DEFAULT_MAX_ITER) -> DDPSolver:
    """The box-FDDP solver of ``task`` on ``horizon`` (default ``task.T``), built once per process."""
    per_task = _CACHE.setdefault(task, {})
    key = (task.T if horizon is None else int(horizon), int(max_iter))
    if key not in per_task:
        per_task[key] = DDPSolver(task, key[0], max_iter=key[1])
    return per_task[key]

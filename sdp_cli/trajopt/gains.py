"""Feedback gains ``K_t = du_t/dx_t`` at a converged trajectory-optimization solution.

The gains are the sensitivities of the optimal control to the current state, i.e. the
solution of the linear-quadratic problem obtained by linearizing the KKT conditions of
OCP (1) at the solution. We compute them with a backward Riccati recursion in the state
tangent space (``ndx``), which handles free-flyer states (``nx != ndx``):

Linearization (per stage ``t``, around the solution ``x_t, u_t``)
    ``A_t = J_-(x_{t+1}) d f(x_t (+) dx, u_t)/d dx``, ``B_t = J_-(x_{t+1}) d f/d u``,
    where ``J_-`` is the left inverse of ``J_+(x) = d (x (+) dx)/d dx |_0`` (identity for
    revolute joints; for a quaternion it maps the ambient 4-vector to the 3-vector).

Second-order terms: the Hessian of the stage LAGRANGIAN, not of the cost alone
    ``L_t(dx, du) = l(x_t (+) dx, u_t + du; xi) + lam_t^T (x_t (+) dx)
    - lam_{t+1}^T f(x_t (+) dx, u_t + du) + mu_t^T h(x_t (+) dx; xi)``,
    with casadi's sign convention (casadi's Lagrangian is ``f + lam_g^T g`` and the gap
    constraints are ``g_t = x_{t+1} - f(x_t, u_t)``, so ``lam_{t+1}`` enters with a minus
    in front of ``f``). ``H_t = d^2 L_t / d(dx, du)^2 |_0``; the terminal stage has
    ``L_T = l_T + lam_T^T (x_T (+) dx) + mu_T^T h``. The term ``lam_t^T (x (+) dx)``
    is the curvature of the chart (zero for revolute joints).

Recursion (t = T-1 .. 0), value Hessian ``P_T = H_T``:
    ``Q_xx = H_xx + A^T P A``, ``Q_ux = H_ux + B^T P A``, ``Q_uu = H_uu + B^T P B``.
    Controls at an active bound (box-constrained DDP) are clamped: their gain rows are
    zero; the free ones get ``K_f = -Q_ff^-1 Q_fx``. The value Hessian is updated with
    the closed loop, ``P = Q_xx + K^T Q_ux + Q_ux^T K + K^T Q_uu K``.

Active state constraints ``h_i(x_s) <= 0`` (with a positive multiplier) are treated as
equalities of the linearized problem: ``C_s dx_s = 0``, ``C_s = dh/dx J_+``. At stage
``t`` the rows ``C_{t+1}`` become ``C_{t+1} (A dx + B du) = 0``: the part that the free
controls can satisfy (row space of ``C_{t+1} B_f``, from an SVD) is imposed on ``du``
(equality-constrained QP, solved through its KKT system); the remainder only involves
``dx_t`` and is pushed to the previous stage as an extra state constraint (the approach
of constrained LQR with state constraints of higher relative degree). Constraints that
reach ``x_0`` are dropped (the initial state is given).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

#: a control is clamped when it lies within this distance (relative to max(1, |bound|))
BOUND_ACTIVE_TOL = 1e-6
#: a state constraint is active when h > -tol and its multiplier > tol
STATE_ACTIVE_TOL = 1e-6


def stage_derivative_functions(task) -> dict[str, ca.Function]:
    """Casadi functions giving the linearization of one stage (SX, not mapped).

    - ``lin_stage(x, u, xi, lam_cur, lam_next, mu) -> (Fx (nx, ndx), Fu (nx, nu), H (ndx+nu, ndx+nu))``
    - ``lin_term(x, xi, lam_cur, mu) -> H_T (ndx, ndx)``
    - ``chart(x) -> (J_+ (nx, ndx), dh (n_h, ndx))``: tangent basis and constraint Jacobian
    """
    nx, ndx, nu, n_h = task.nx, task.ndx, task.nu, task.n_h
    x, u, xi = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("xi", task.n_xi)
    lam_cur, lam_next, mu = ca.SX.sym("lam_cur", nx), ca.SX.sym("lam_next", nx), ca.SX.sym("mu", n_h)
    dx, du = ca.SX.sym("dx", ndx), ca.SX.sym("du", nu)
    xx = task.f_integrate(x, dx)
    uu = u + du
    fx = task.f_step(xx, uu)
    h = task.f_state_constraints(xx, xi)
    lag = task.f_running_cost(xx, uu, xi) + ca.dot(lam_cur, xx) - ca.dot(lam_next, fx)
    if n_h:
        lag = lag + ca.dot(mu, h)
    z = ca.vertcat(dx, du)
    zero = ca.DM.zeros(ndx + nu)
    Fx, Fu, H = ca.substitute([ca.jacobian(fx, dx), ca.jacobian(fx, du), ca.hessian(lag, z)[0]], [z], [zero])
    lin_stage = ca.Function("lin_stage", [x, u, xi, lam_cur, lam_next, mu], [Fx, Fu, H],
                            ["x", "u", "xi", "lam_cur", "lam_next", "mu"], ["Fx", "Fu", "H"])
    lag_T = task.f_terminal_cost(xx, xi) + ca.dot(lam_cur, xx)
    if n_h:
        lag_T = lag_T + ca.dot(mu, h)
    HT = ca.substitute(ca.hessian(lag_T, dx)[0], dx, ca.DM.zeros(ndx))
    lin_term = ca.Function("lin_term", [x, xi, lam_cur, mu], [HT], ["x", "xi", "lam_cur", "mu"], ["H"])
    Jp, dh = ca.substitute([ca.jacobian(xx, dx), ca.jacobian(h, dx)], [dx], [ca.DM.zeros(ndx)])
    chart = ca.Function("chart", [x, xi], [Jp, dh], ["x", "xi"], ["Jplus", "dh"])
    return {"lin_stage": lin_stage, "lin_term": lin_term, "chart": chart}


def riccati_function(ndx: int, nu: int, T: int) -> ca.Function:
    """The recursion without state constraints as one casadi function (compiled with the NLP).

    ``riccati(P_T (ndx, ndx), A, B, H, free) -> (P, K)`` with the stages given in REVERSED
    order (t = T-1 first) and horizontally stacked: A (ndx, T ndx), B (ndx, T nu),
    H (ndx+nu, T (ndx+nu)), free (nu, T) in {0, 1}; outputs P_{T-1..0} (ndx, T ndx) and
    K_{T-1..0} (nu, T ndx). Clamped controls are removed by masking:
    ``Q_uu -> M Q_uu M + (I - M)``, ``Q_ux -> M Q_ux`` with ``M = diag(free)``, whose
    solution has zero rows where clamped and ``-Q_ff^-1 Q_fx`` elsewhere.
    """
    P, A, B = ca.SX.sym("P", ndx, ndx), ca.SX.sym("A", ndx, ndx), ca.SX.sym("B", ndx, nu)
    H, free = ca.SX.sym("H", ndx + nu, ndx + nu), ca.SX.sym("free", nu)
    PA = ca.mtimes(P, A)
    Qxx = H[:ndx, :ndx] + ca.mtimes(A.T, PA)
    Qux = H[ndx:, :ndx] + ca.mtimes(B.T, PA)
    Quu = H[ndx:, ndx:] + ca.mtimes([B.T, P, B])
    M = ca.diag(free)
    K = -ca.solve(ca.mtimes([M, Quu, M]) + ca.diag(1 - free), ca.mtimes(M, Qux))
    KtQux = ca.mtimes(K.T, Qux)
    Pn = Qxx + KtQux + KtQux.T + ca.mtimes([K.T, Quu, K])
    step = ca.Function("riccati_step", [P, A, B, H, free], [0.5 * (Pn + Pn.T), K])
    return step.mapaccum("riccati", T)


def riccati_gains_fast(fun: ca.Function, A, B, H, HT, clamped) -> np.ndarray:
    """:func:`riccati_gains` without state constraints through :func:`riccati_function`."""
    T, ndx, nu = B.shape

    def cat(M):  # (T, r, c) reversed in time -> (r, T c)
        M = M[::-1]
        return M.transpose(1, 0, 2).reshape(M.shape[1], -1)

    _, K = fun(0.5 * (HT + HT.T), cat(A), cat(B), cat(H), (~clamped[::-1]).T.astype(float))
    return _stack(K, T, nu, ndx)[::-1]


def _stack(M, n: int, rows: int, cols: int) -> np.ndarray:
    """casadi horizontally-stacked ``(rows, n*cols)`` -> ``(n, rows, cols)``."""
    return np.asarray(M).reshape(rows, n, cols).transpose(1, 0, 2)


def linearize(funcs: dict[str, ca.Function], task, X, U, xi, lam_gap, lam_init, mu_h):
    """Tangent-space linearization along a solution.

    Shapes: X (T+1, nx), U (T, nu), xi (n_xi,), lam_gap (T, nx) multipliers of
    ``x_{t+1} - f(x_t, u_t)``, lam_init (nx,) of ``x_0 - x0_hat``, mu_h (T, n_h) of
    ``h(x_1..x_T)``. ``funcs`` holds mapped versions ``lin_stage_map``,
    ``lin_term``, ``chart_map`` (T+1 columns).
    Returns A (T, ndx, ndx), B (T, ndx, nu), H (T, ndx+nu, ndx+nu), HT (ndx, ndx),
    dh (T+1, n_h, ndx).
    """
    T, nx, ndx, nu, n_h = len(U), task.nx, task.ndx, task.nu, task.n_h
    lam_cur = np.vstack([lam_init[None], lam_gap[:-1]])  # multiplier attached to x_t, t < T
    mu = np.vstack([np.zeros((1, n_h)), mu_h[:-1]])  # no state constraint on x_0
    xis = np.repeat(xi[:, None], T, 1)
    Fx, Fu, H = funcs["lin_stage_map"](X[:-1].T, U.T, xis, lam_cur.T, lam_gap.T, mu.T)
    Fx, Fu, H = _stack(Fx, T, nx, ndx), _stack(Fu, T, nx, nu), _stack(H, T, ndx + nu, ndx + nu)
    HT = np.asarray(funcs["lin_term"](X[-1], xi, lam_gap[-1], mu_h[-1]))
    Jp, dh = funcs["chart_map"](X.T, np.repeat(xi[:, None], T + 1, 1))
    Jp, dh = _stack(Jp, T + 1, nx, ndx), _stack(dh, T + 1, n_h, ndx)
    if nx == ndx and np.allclose(Jp, np.eye(nx), rtol=0, atol=1e-14):
        A, B = Fx, Fu
    else:
        Jm = np.linalg.pinv(Jp[1:])  # (T, ndx, nx) left inverses at x_{t+1}
        A, B = Jm @ Fx, Jm @ Fu
    return A, B, H, HT, dh


def active_controls(U, u_lb, u_ub) -> np.ndarray:
    """Clamped-control mask (T, nu): controls at a bound, within ``BOUND_ACTIVE_TOL``
    relative to ``max(1, |bound|)`` (interior-point solutions approach active bounds to
    about ``mu / multiplier``)."""
    tol_ub = BOUND_ACTIVE_TOL * np.maximum(1.0, np.abs(u_ub))
    tol_lb = BOUND_ACTIVE_TOL * np.maximum(1.0, np.abs(u_lb))
    return (U >= u_ub - tol_ub) | (U <= u_lb + tol_lb)


def _constrained_gain(Qff, Qfx, E, F):
    """argmin_du 1/2 du^T Qff du + du^T Qfx dx  s.t. E du = -F dx  ->  du = K dx."""
    nf, m = Qff.shape[0], E.shape[0]
    if m == 0:
        try:
            return -np.linalg.solve(Qff, Qfx)
        except np.linalg.LinAlgError:
            return -np.linalg.lstsq(Qff, Qfx, rcond=None)[0]
    KKT = np.block([[Qff, E.T], [E, np.zeros((m, m))]])
    rhs = np.vstack([Qfx, F])
    try:
        sol = np.linalg.solve(KKT, rhs)
    except np.linalg.LinAlgError:
        sol = np.linalg.lstsq(KKT, rhs, rcond=None)[0]
    return -sol[:nf]


def riccati_gains(A, B, H, HT, clamped, C=None, rank_tol: float = 1e-9):
    """Backward Riccati recursion (see the module docstring).

    A (T, ndx, ndx), B (T, ndx, nu), H (T, ndx+nu, ndx+nu) stage Lagrangian Hessians in
    (dx, du) order, HT (ndx, ndx), clamped (T, nu) bool, C: optional list of T+1 arrays
    (n_active_t, ndx) of active state-constraint rows (index 0 ignored).
    Returns K (T, nu, ndx) and the value Hessians P (T+1, ndx, ndx).
    """
    T, ndx, nu = B.shape
    K = np.zeros((T, nu, ndx))
    P = np.zeros((T + 1, ndx, ndx))
    P[T] = 0.5 * (HT + HT.T)
    rows = C[T] if C is not None else np.zeros((0, ndx))
    for t in reversed(range(T)):
        At, Bt, Ht, Pn = A[t], B[t], H[t], P[t + 1]
        Qxx = Ht[:ndx, :ndx] + At.T @ Pn @ At
        Qux = Ht[ndx:, :ndx] + Bt.T @ Pn @ At
        Quu = Ht[ndx:, ndx:] + Bt.T @ Pn @ Bt
        free = ~clamped[t]
        Kt = np.zeros((nu, ndx))
        carry = np.zeros((0, ndx))
        Dx, Du = rows @ At, rows @ Bt[:, free]
        if rows.shape[0]:
            Uu, s, _ = np.linalg.svd(Du, full_matrices=True)
            r = int(np.sum(s > rank_tol * max(1.0, s.max(initial=0.0))))
            E, F = Uu[:, :r].T @ Du, Uu[:, :r].T @ Dx
            carry = Uu[:, r:].T @ Dx
            carry = carry[np.linalg.norm(carry, axis=1) > rank_tol]
        else:
            E, F = np.zeros((0, int(free.sum()))), np.zeros((0, ndx))
        if free.any():
            Kt[free] = _constrained_gain(Quu[np.ix_(free, free)], Qux[free], E, F)
        K[t] = Kt
        Pt = Qxx + Kt.T @ Qux + Qux.T @ Kt + Kt.T @ Quu @ Kt
        P[t] = 0.5 * (Pt + Pt.T)
        own = C[t] if (C is not None and t > 0) else np.zeros((0, ndx))
        rows = np.vstack([own, carry]) if t > 0 else np.zeros((0, ndx))
    return K, P

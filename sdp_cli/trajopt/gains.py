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
    ``L_t(x, u) = l(x, u; xi) - lam_{t+1}^T f(x, u) + mu_t^T h(x; xi)``
    with casadi's sign convention (casadi's Lagrangian is ``f + lam_g^T g`` and the gap
    constraints are ``g_t = x_{t+1} - f(x_t, u_t)``, so ``lam_{t+1}`` enters with a minus
    in front of ``f``), ``L_T = l_T + mu_T^T h``; these are the diagonal blocks of the
    NLP's Hessian, reused from the compiled library. In the tangent space
    ``H_t = blkdiag(J_+, I)^T d^2 L_t blkdiag(J_+, I)`` (exact at a KKT point).

Recursion (t = T-1 .. 0), value Hessian ``P_T = H_T``:
    ``Q_xx = H_xx + A^T P A``, ``Q_ux = H_ux + B^T P A``, ``Q_uu = H_uu + B^T P B``.
    Controls at an active bound (box-constrained DDP) are clamped: their gain rows are
    zero; the free ones get ``K_f = -Q_ff^-1 Q_fx``. The value Hessian is updated with
    the closed loop, ``P = Q_xx + K^T Q_ux + Q_ux^T K + K^T Q_uu K``.

Active state constraints ``h_i(x_s) <= 0`` (multiplier larger than the slack ``-h_i``, the
same interior-point criterion as for the control bounds, see :func:`active_controls`) are treated as
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
#: an inequality is undecided when neither its multiplier nor its slack dominates the other
#: by this factor (see :func:`ambiguous`)
AMBIGUITY_RATIO = 1e4


def chart_function(task) -> ca.Function:
    """``chart(x, xi) -> (J_+ (nx, ndx), dh (n_h, ndx))``: the tangent basis
    ``d (x (+) dx)/d dx |_0`` and the state-constraint Jacobian in the tangent space."""
    x, xi, dx = ca.SX.sym("x", task.nx), ca.SX.sym("xi", task.n_xi), ca.SX.sym("dx", task.ndx)
    xx = task.f_integrate(x, dx)
    h = task.f_state_constraints(xx, xi)
    Jp, dh = ca.substitute([ca.jacobian(xx, dx), ca.jacobian(h, dx)], [dx], [ca.DM.zeros(task.ndx)])
    return ca.Function("sdp_chart", [x, xi], [Jp, dh], ["x", "xi"], ["Jplus", "dh"])


def linearize(funcs: dict[str, ca.Function], task, X, U, xi, lam_gap, mu_h):
    """Tangent-space linearization along a solution.

    Shapes: X (T+1, nx), U (T, nu), xi (n_xi,), lam_gap (T, nx) multipliers of
    ``x_{t+1} - f(x_t, u_t)``, mu_h (T, n_h) of ``h(x_1..x_T)``. ``funcs``: the mapped
    ambient stage blocks of :func:`sdp_cli.trajopt.ocp.stage_blocks` (``jac_f_map``,
    ``hess_stage_map``, ``hess_term``) and ``chart_map`` (T+1 columns).

    The ambient Lagrangian Hessian (without the linear terms ``lam_t^T x_t``) is pulled
    back to the tangent space as ``J_+^T H J_+``: exact at a KKT point, where the stage
    gradient that multiplies the chart's curvature vanishes. For revolute joints
    ``J_+ = I`` and nothing changes.
    Returns A (T, ndx, ndx), B (T, ndx, nu), H (T, ndx+nu, ndx+nu), HT (ndx, ndx),
    dh (T+1, n_h, ndx).
    """
    T, nx, ndx, nu, n_h = len(U), task.nx, task.ndx, task.nu, task.n_h
    s = nx + nu
    xis = np.repeat(xi[:, None], T + 1, 1)
    mu = np.vstack([np.zeros((1, n_h)), mu_h[:-1]])  # no state constraint on x_0
    Fx, Fu = funcs["jac_f_map"](X[:-1].T, U.T)
    Fx, Fu = _stack(ca.densify(Fx), T, nx, nx), _stack(ca.densify(Fu), T, nx, nu)
    H = _stack(ca.densify(funcs["hess_stage_map"](X[:-1].T, U.T, xis[:, :T], lam_gap.T, np.ones((1, T)), mu.T)),
               T, s, s)
    HT = np.asarray(ca.densify(funcs["hess_term"](X[-1], xi, 1.0, mu_h[-1])))
    Jp, dh = funcs["chart_map"](X.T, xis)
    Jp, dh = _stack(ca.densify(Jp), T + 1, nx, ndx), _stack(ca.densify(dh), T + 1, n_h, ndx)
    if nx == ndx and np.array_equal(Jp, np.broadcast_to(np.eye(nx), Jp.shape)):
        return Fx, Fu, H, HT, dh
    Jm = np.linalg.pinv(Jp[1:])  # (T, ndx, nx) left inverses at x_{t+1}
    A, B = Jm @ Fx @ Jp[:-1], Jm @ Fu
    Z = np.zeros((T, s, ndx + nu))
    Z[:, :nx, :ndx] = Jp[:-1]
    Z[:, nx:, ndx:] = np.eye(nu)
    return A, B, Z.transpose(0, 2, 1) @ H @ Z, Jp[-1].T @ HT @ Jp[-1], dh


def active_controls(U, u_lb, u_ub, lam_u=None) -> np.ndarray:
    """Clamped-control mask (T, nu).

    With the bound multipliers ``lam_u`` (casadi's ``lam_x``: > 0 at an upper bound, < 0
    at a lower one) a bound counts as active when its multiplier exceeds its slack: an
    interior-point solution has ``z s ~ mu``, so active bounds have ``z >> s`` and inactive
    ones ``z << s`` whatever the final ``mu`` (a fixed distance threshold misclassifies
    controls that approach their bound as ``mu / z`` at loose tolerances). Without
    multipliers: within ``BOUND_ACTIVE_TOL`` of the bound (relative to ``max(1, |bound|)``).
    """
    if lam_u is None:
        tol_ub = BOUND_ACTIVE_TOL * np.maximum(1.0, np.abs(u_ub))
        tol_lb = BOUND_ACTIVE_TOL * np.maximum(1.0, np.abs(u_lb))
        return (U >= u_ub - tol_ub) | (U <= u_lb + tol_lb)
    s_ub, s_lb = u_ub - U, U - u_lb
    return ((lam_u > 0) & (lam_u > s_ub)) | ((lam_u < 0) & (-lam_u > s_lb))


def ambiguous(z, s) -> np.ndarray:
    """Inequalities whose activity an interior point leaves undecided: multiplier ``z >= 0``
    and slack ``s >= 0`` within ``AMBIGUITY_RATIO`` of each other. At an interior point
    ``z s ~ mu``; a clearly active constraint has ``z >> s``, a clearly inactive one
    ``z << s``. Fatrop stopped at tol 1e-6 leaves ``z s ~ 1e-7``: on quadrotor-1 its active
    thrust bounds had z/s of only 1 to 1e4, the misclassified ones 2e-3 to 0.9 (e.g. z 4.7e-5,
    s 4.6e-3 N), so nearly every quadrotor and double-pendulum solve is polished."""
    z, s = np.abs(np.asarray(z, float)), np.maximum(np.asarray(s, float), 0.0)
    big, small = np.maximum(z, s), np.minimum(z, s)
    return (small * AMBIGUITY_RATIO > big) & (big > 0)


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


def set_solution_gains(res, task, gfun: dict, riccati, lam_gap: np.ndarray, mu_h: np.ndarray) -> None:
    """``res.A, res.B, res.K, res.Phi`` of a converged solution ``res`` (a :class:`~sdp_cli.trajopt.solver.SolveResult`
    with ``clamped`` and ``active_h`` set) from its multipliers: :func:`linearize` (``gfun``), then the Riccati
    recursion with the active state constraints as equalities (:func:`riccati_gains`), or without any through the
    compiled ``riccati`` (:func:`riccati_gains_fast`). A failure is told in ``res.status``, the gains left NaN."""
    T = len(res.U)
    try:
        A, B, H, HT, dh = linearize(gfun, task, res.X, res.U, res.xi, lam_gap, mu_h)
        if res.active_h.any():
            C = [np.zeros((0, task.ndx))] + [dh[t + 1][res.active_h[t]] for t in range(T)]
            K, _ = riccati_gains(A, B, H, HT, res.clamped, C)
        else:
            K = riccati_gains_fast(riccati, A, B, H, HT, res.clamped)
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise np.linalg.LinAlgError("non-finite linearization")
    except np.linalg.LinAlgError as e:
        res.status += f"; gains unavailable ({e})"
    else:
        res.K, res.A, res.B, res.Phi = K, A, B, A + B @ K

"""The casadi functions box-FDDP (:mod:`sdp_cli.trajopt.ddp`) evaluates, compiled once per task family and
horizon, and their tangent-space form.

Vector-space tasks without state constraints (the pendulums, UR5): ambient = tangent coordinates, and the
functions are used as they are. A task whose state lives on a manifold (``nx != ndx``: the quadrotor's SE(3)
base) or that has state constraints ``h(x) <= 0`` also gets ``sdp_ddp_chart``, and the DDP works in the tangent
space ``dx`` of ``x (+) dx`` (:meth:`Task.integrate`), as the gains do (:mod:`sdp_cli.trajopt.gains`):

- ``J_+(x) = d (x (+) dx)/d dx |_0`` (nx, ndx) and its left inverse ``J_-(x) = (J_+' J_+)^-1 J_+'``;
- ``A_t = J_-(x_{t+1}) f_x J_+(x_t)``, ``B_t = J_-(x_{t+1}) f_u`` (exact at a feasible iterate; with gaps, the
  tangent space of ``x_{t+1}`` stands for that of ``f(x_t, u_t)``, a first-order difference);
- cost derivatives pulled back, ``l_x <- J_+' l_x``, ``l_xx <- J_+' l_xx J_+`` (Gauss-Newton: the chart's
  curvature times the gradient is left out, as the dynamics' second derivatives are);
- the gaps in the tangent space: ``fbar_{t+1} = J_-(x_{t+1}) (f(x_t, u_t) - x_{t+1})`` (zero exactly when the
  ambient gap is), and the rollout closes them on the manifold,
  ``x^_{t+1} = f(x^_t, u^_t) (+) (-(1 - a) fbar_{t+1})``, so that every iterate keeps unit quaternions;
- the feedback acts on ``J_-(x_t) (x^_t - x_t)``, the chart's first-order difference (``K_t J_-(x_t)`` enters the
  compiled rollout as an ambient gain).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from sdp_cli.trajopt import gains as _gains
from sdp_cli.trajopt.ocp import stage_blocks


def general(task) -> bool:
    """Whether ``task`` needs the tangent-space and constrained path (a manifold or state constraints)."""
    return task.nx != task.ndx or task.n_h > 0


def gauss_newton(task) -> bool:
    """Whether ``task`` declares its costs as residuals (:meth:`~sdp_cli.tasks.base.Task._running_residual`),
    so that box-FDDP can iterate with the Gauss-Newton model of their Hessians."""
    x, u, xi = ca.SX.sym("x", task.nx), ca.SX.sym("u", task.nu), ca.SX.sym("xi", task.n_xi)
    return task._running_residual(x, u, xi) is not None and task._terminal_residual(x, xi) is not None


def ddp_functions(task, T: int, hessian: str = "psd") -> list[ca.Function]:
    """The functions box-FDDP evaluates:

    - ``sdp_ddp_stage(x, u, xi) -> (f, A, B, l, l_x, l_u, l_xx, l_uu, l_ux)`` (ambient derivatives; with
      ``hessian="gn"`` the cost Hessian blocks are the Gauss-Newton ``r_z' r_z`` of the task's residuals)
    - ``sdp_ddp_term(x, xi) -> (l_T, l_Tx, l_Txx)`` (likewise), and with ``"gn"``
      ``sdp_ddp_term_exact(x, xi) -> l_Txx`` (the exact terminal Hessian, for the stored gains)
    - ``sdp_ddp_step(x, u) -> f``
    - ``sdp_ddp_hess(x, u, xi, lam) -> d^2/d(x,u)^2 [l - lam' f]`` (the exact Hessian of the gains)
    - ``sdp_ddp_roll_T<T>(x^_0, U, k, K, X, gaps, alpha, xi) -> (X^_{1..T} (nx, T), U^ (nu, T), cost)``: the
      forward pass of one step ``alpha`` as one call (a casadi ``mapaccum`` over t: a loop in the generated
      code), stages horizontally stacked, ``K_t`` as ``vec(K_t)`` (column-major, ambient), ``gaps`` =
      ``fbar_{1..T}`` (tangent)
    - ``sdp_ddp_riccati_T<T>``: :func:`sdp_cli.trajopt.gains.riccati_function` (the gains' recursion)

    and, for a :func:`general` task, ``sdp_ddp_chart(x, xi) -> (J_+ (nx, ndx), h (n_h), dh/d dx (n_h, ndx))``,
    ``sdp_ddp_h(x, xi) -> h``
    and the blocks of :func:`sdp_cli.trajopt.gains.linearize` (``sdp_jac_f``, ``sdp_hess_stage``,
    ``sdp_hess_term``, ``sdp_jac_h``; its chart is ``sdp_ddp_chart``'s): the gains at a constrained or manifold
    solution are computed as fatrop's, from the ambient multipliers (:func:`ambient_costates`).
    """
    x, u, xi = ca.SX.sym("x", task.nx), ca.SX.sym("u", task.nu), ca.SX.sym("xi", task.n_xi)
    lam = ca.SX.sym("lam", task.nx)
    f = task.f_step(x, u)
    l_run = task.f_running_cost(x, u, xi)
    l_T = task.f_terminal_cost(x, xi)
    lu = ca.gradient(l_run, u)
    first = [f, ca.jacobian(f, x), ca.jacobian(f, u), l_run, ca.gradient(l_run, x), lu]
    if hessian == "gn":
        # the residual Jacobians in SX, their products r_z' r_z as dense matrix products (MX) in the generated
        # code rather than multiplied out entry by entry into scalar expressions
        r, r_T = task._running_residual(x, u, xi), task._terminal_residual(x, xi)
        sx_stage = ca.Function("s", [x, u, xi], first + [ca.jacobian(r, x), ca.jacobian(r, u)])
        sx_term = ca.Function("t", [x, xi], [l_T, ca.gradient(l_T, x), ca.jacobian(r_T, x)])
        xm, um, xim = ca.MX.sym("x", task.nx), ca.MX.sym("u", task.nu), ca.MX.sym("xi", task.n_xi)
        *head, rx, ru = sx_stage(xm, um, xim)
        stage = ca.Function("sdp_ddp_stage", [xm, um, xim],
                            head + [ca.mtimes(rx.T, rx), ca.mtimes(ru.T, ru), ca.mtimes(ru.T, rx)])
        lT, lTx, rTx = sx_term(xm, xim)
        term = ca.Function("sdp_ddp_term", [xm, xim], [lT, lTx, ca.mtimes(rTx.T, rTx)])
    else:
        stage = ca.Function("sdp_ddp_stage", [x, u, xi],
                            first + [ca.hessian(l_run, x)[0], ca.hessian(l_run, u)[0], ca.jacobian(lu, x)])
        term = ca.Function("sdp_ddp_term", [x, xi], [l_T, ca.gradient(l_T, x), ca.hessian(l_T, x)[0]])
    step = ca.Function("sdp_ddp_step", [x, u], [f])
    z = ca.vertcat(x, u)
    hess = ca.Function("sdp_ddp_hess", [x, u, xi, lam], [ca.hessian(l_run - ca.dot(lam, f), z)[0]])
    # one closed-loop step of the forward pass, accumulated over t
    ng = task.ndx
    xh, u_old, k, Kv, x_old, gap = (ca.SX.sym(nm, d) for nm, d in (("xh", task.nx), ("u_old", task.nu),
                                    ("k", task.nu), ("K", task.nu * task.nx), ("x_old", task.nx), ("gap", ng)))
    alpha = ca.SX.sym("alpha")
    uh = u_old + alpha * k + ca.mtimes(ca.reshape(Kv, task.nu, task.nx), xh - x_old)
    uh = ca.fmin(ca.fmax(uh, ca.DM(task.u_lb)), ca.DM(task.u_ub))
    nxt = (task.f_integrate(task.f_step(xh, uh), -(1 - alpha) * gap) if task.nx != task.ndx
           else task.f_step(xh, uh) - (1 - alpha) * gap)
    closed = ca.Function("sdp_ddp_closed", [xh, u_old, k, Kv, x_old, gap, alpha, xi],
                         [nxt, uh, task.f_running_cost(xh, uh, xi)])
    acc = closed.mapaccum("sdp_ddp_acc", T)
    x0h = ca.SX.sym("x0h", task.nx)
    Us, ks, Ks = ca.SX.sym("U", task.nu, T), ca.SX.sym("k", task.nu, T), ca.SX.sym("Kv", task.nu * task.nx, T)
    Xs, gs = ca.SX.sym("X", task.nx, T), ca.SX.sym("gaps", ng, T)
    Xn, Un, ls = acc(x0h, Us, ks, Ks, Xs, gs, ca.repmat(alpha, 1, T), ca.repmat(xi, 1, T))
    roll = ca.Function(f"sdp_ddp_roll_T{T}", [x0h, Us, ks, Ks, Xs, gs, alpha, xi],
                       [Xn, Un, ca.sum2(ls) + task.f_terminal_cost(Xn[:, -1], xi)])
    riccati = _gains.riccati_function(task.ndx, task.nu, T)
    args = riccati.mx_in()
    riccati = ca.Function(f"sdp_ddp_riccati_T{T}", args, riccati.call(args))
    funcs = [stage, term, step, hess, roll, riccati]
    if hessian == "gn":
        funcs.append(ca.Function("sdp_ddp_term_exact", [x, xi], [ca.hessian(l_T, x)[0]]))
    if general(task):
        dx = ca.SX.sym("dx", task.ndx)
        xx = task.f_integrate(x, dx)
        h = task.f_state_constraints(x, xi) if task.n_h else ca.SX(0, 1)
        hh = task.f_state_constraints(xx, xi) if task.n_h else ca.SX(0, 1)
        Jp, dh = ca.substitute([ca.jacobian(xx, dx), ca.jacobian(hh, dx)], [dx], [ca.DM.zeros(task.ndx)])
        funcs += [ca.Function("sdp_ddp_chart", [x, xi], [Jp, h, dh]), ca.Function("sdp_ddp_h", [x, xi], [h])]
        funcs += stage_blocks(task)
    return funcs


class DenseCall:
    """A casadi ``Function`` called with numpy inputs, returning numpy outputs through its buffer (no copy
    through Python lists: ``np.asarray`` of a ``casadi.DM`` took 10x the evaluation itself on a quadrotor
    batch). Same shapes as ``np.asarray`` of the ``DM`` outputs (one array, or a tuple); bit-identical values
    (the same evaluation). Sparse outputs (structural zeros: the quadrotor's Jacobians and Hessians) are
    densified by a wrapper function (the zeros written as 0.0, as ``np.asarray`` writes them); a function with a
    sparse input is called the usual way."""

    def __init__(self, f):
        dense_in = all(f.sparsity_in(i).is_dense() for i in range(f.n_in()))
        self.densified = dense_in and not all(f.sparsity_out(i).is_dense() for i in range(f.n_out()))
        if self.densified:
            ins = [ca.MX.sym(f"in{i}", f.sparsity_in(i)) for i in range(f.n_in())]
            f = ca.Function(f.name() + "_dense", ins, [ca.densify(o) for o in f.call(ins)])
        self.f = f
        self.dense = dense_in          # (its outputs are dense now)
        if self.dense:
            self.buf, self.run = f.buffer()

    def __call__(self, *args):
        f = self.f
        if not self.dense:
            out = f(*args)
            return tuple(np.asarray(o) for o in out) if isinstance(out, (tuple, list)) else np.asarray(out)
        ins = []
        for i, a in enumerate(args):
            r, c = f.size_in(i)
            a = np.ascontiguousarray(np.asarray(a, dtype=float).reshape(r, c).T)   # column-major (r, c)
            self.buf.set_arg(i, memoryview(a))
            ins.append(a)
        outs = []
        for j in range(f.n_out()):
            r, c = f.size_out(j)
            o = np.empty((c, r))
            self.buf.set_res(j, memoryview(o))
            outs.append(o)
        self.run()
        # a densified function's outputs in C order, as np.asarray of its DM outputs gave them (numpy's kernels
        # round differently on other memory layouts: the solver's iterates would not stay bit-identical)
        res = tuple(np.ascontiguousarray(o.T) if self.densified else o.T for o in outs)
        return res[0] if len(res) == 1 else res


def cols(M, n: int, rows: int, cols: int) -> np.ndarray:
    """casadi's horizontally stacked map output ``(rows, n cols)`` -> ``(n, rows, cols)``."""
    return np.asarray(M).reshape(rows, n, cols).transpose(1, 0, 2)


def left_inverse(Jp: np.ndarray) -> np.ndarray:
    """``J_- = (J_+' J_+)^-1 J_+'`` of a batch ``(..., nx, ndx)`` -> ``(..., ndx, nx)``."""
    Jt = np.swapaxes(Jp, -1, -2)
    return np.linalg.solve(Jt @ Jp, Jt)


def to_tangent(d: dict, Jp: np.ndarray, Jm: np.ndarray) -> None:
    """Pull ``d``'s ambient derivatives (:meth:`DDPSolver._derivatives`) back to the tangent space, in place:
    ``Jp (n, T+1, nx, ndx)`` = ``J_+`` at ``x_0..x_T``, ``Jm`` its left inverses."""
    Jx, JxT = Jp[:, :-1], np.swapaxes(Jp[:, :-1], -1, -2)
    d["A"] = Jm[:, 1:] @ d["A"] @ Jx
    d["B"] = Jm[:, 1:] @ d["B"]
    d["lx"] = np.matmul(JxT, d["lx"][..., None])[..., 0]
    d["lxx"] = JxT @ d["lxx"] @ Jx
    d["lux"] = d["lux"] @ Jx
    JT = Jp[:, -1]
    d["lTx"] = np.matmul(np.swapaxes(JT, -1, -2), d["lTx"][..., None])[..., 0]
    d["lTxx"] = np.swapaxes(JT, -1, -2) @ d["lTxx"] @ JT


def ambient_costates(Fx: np.ndarray, lx: np.ndarray, lTx: np.ndarray, dh: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """The multipliers ``lam (T, nx)`` of ``x_{t+1} - f(x_t, u_t) = 0`` in the ambient coordinates (casadi's sign,
    as fatrop returns them) at a solution, from the adjoint recursion of the ambient Lagrangian's stationarity
    in ``x_1..x_T``: ``lam_{T-1} = -(l_Tx + dh_T' mu_T)``, ``lam_{t-1} = F_x(t)' lam_t - l_x(t) - dh_t' mu_t``.

    The DDP's co-states ``V_x`` are their tangent part (``J_+' lam = -V_x``); the gains also need the part
    normal to the manifold (a quaternion's radial direction), which multiplies the chart's curvature in the
    pulled-back Hessian. ``Fx (T, nx, nx)``, ``lx (T, nx)`` at ``x_0..x_{T-1}``; ``dh (T, n_h, nx)``,
    ``mu (T, n_h)`` at ``x_1..x_T``."""
    T = len(Fx)
    lam = np.zeros((T, Fx.shape[1]))
    lam[-1] = -(lTx + dh[-1].T @ mu[-1])
    for t in range(T - 1, 0, -1):
        lam[t - 1] = Fx[t].T @ lam[t] - lx[t] - dh[t - 1].T @ mu[t - 1]
    return lam

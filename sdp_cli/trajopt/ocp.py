"""Multiple-shooting transcription of OCP (1) as a parametric casadi NLP.

Decision variables, stage-wise (the order fatrop's structure needs, fine for IPOPT too)::

    w = [x_0, u_0, x_1, u_1, ..., x_{T-1}, u_{T-1}, x_T]            (T+1) nx + T nu

Constraints ``g``, stage-wise: the gap ``x_{k+1} - f(x_k, u_k)`` of stage k, then the path
constraints of stage k (stage 0: ``x_0 - x0_hat``; stage k >= 1: ``h(x_k; xi)``), and
finally ``h(x_T; xi)``::

    g = [gap_0, x_0 - x0_hat, gap_1, h(x_1), ..., gap_{T-1}, h(x_{T-1}), h(x_T)]

Gaps and ``x_0`` are equalities (``lbg = ubg = 0``), ``h <= 0``. Control bounds are
variable bounds. Parameters ``p = [x0_hat (nx), xi (n_xi)]``: a new task instance or
initial state changes only numbers, never the NLP.

The NLP is built from ``map``-ped stage functions in an MX graph, so its generated C code
(see :mod:`sdp_cli.trajopt.jit`) is one loop per stage function, whatever ``T``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np


@dataclass(frozen=True)
class Layout:
    """Index bookkeeping of ``w`` and ``g`` for horizon ``T``."""

    T: int
    nx: int
    nu: int
    n_h: int

    @property
    def nw(self) -> int:
        return (self.T + 1) * self.nx + self.T * self.nu

    @property
    def ng(self) -> int:
        return (self.T + 1) * self.nx + self.T * self.n_h

    def x_index(self) -> np.ndarray:
        """(T+1, nx) positions of the states in ``w``."""
        s = self.nx + self.nu
        return np.arange(self.T + 1)[:, None] * s + np.arange(self.nx)[None]

    def u_index(self) -> np.ndarray:
        """(T, nu) positions of the controls in ``w``."""
        s = self.nx + self.nu
        return np.arange(self.T)[:, None] * s + self.nx + np.arange(self.nu)[None]

    def g_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row positions in ``g``: gaps (T, nx), init (nx,), h of x_1..x_T (T, n_h)."""
        nx, n_h, T = self.nx, self.n_h, self.T
        gap, h = np.zeros((T, nx), dtype=int), np.zeros((T, n_h), dtype=int)
        gap[0] = np.arange(nx)
        init = nx + np.arange(nx)
        r = 2 * nx
        for t in range(1, T):
            gap[t] = r + np.arange(nx)
            h[t - 1] = r + nx + np.arange(n_h)
            r += nx + n_h
        h[T - 1] = r + np.arange(n_h)
        return gap, init, h

    def equality(self) -> np.ndarray:
        """(ng,) bool: which rows of ``g`` are equalities."""
        eq = np.ones(self.ng, dtype=bool)
        eq[self.g_index()[2].ravel()] = False
        return eq

    def pack(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        w = np.empty(self.nw)
        w[self.x_index()] = X
        w[self.u_index()] = U
        return w

    def unpack(self, w) -> tuple[np.ndarray, np.ndarray]:
        w = np.asarray(w, dtype=float).ravel()
        return w[self.x_index()], w[self.u_index()]

    def fatrop_structure(self) -> dict:
        """The ``N, nx, nu, ng`` options of fatrop's manual structure detection."""
        T = self.T
        return {"structure_detection": "manual", "N": T, "nx": [self.nx] * (T + 1),
                "nu": [self.nu] * T + [0], "ng": [self.nx] + [self.n_h] * T}


def build_nlp(task, T: int) -> tuple[dict, Layout]:
    """The NLP ``{"x": w, "p": p, "f": J, "g": g}`` of the task on horizon ``T`` (MX graph)."""
    nx, nu, n_h = task.nx, task.nu, task.n_h
    lay = Layout(T, nx, nu, n_h)
    w = ca.MX.sym("w", lay.nw)
    p = ca.MX.sym("p", nx + task.n_xi)
    x0_hat, xi = p[:nx], p[nx:]
    XU = ca.reshape(w[: T * (nx + nu)], nx + nu, T)
    X, U = XU[:nx, :], XU[nx:, :]
    xT = w[T * (nx + nu):]
    Xn = ca.horzcat(X[:, 1:], xT)  # x_1 .. x_T
    xis = ca.repmat(xi, 1, T)
    gap = Xn - task.f_step.map(T)(X, U)
    J = ca.sum2(task.f_running_cost.map(T)(X, U, xis)) + task.f_terminal_cost(xT, xi)
    parts = [gap[:, 0], X[:, 0] - x0_hat]
    if n_h:
        Hn = task.f_state_constraints.map(T)(Xn, xis)  # h(x_1) .. h(x_T)
        if T > 1:
            parts.append(ca.vec(ca.vertcat(gap[:, 1:], Hn[:, : T - 1])))
        parts.append(Hn[:, T - 1])
    elif T > 1:
        parts.append(ca.vec(gap[:, 1:]))
    return {"x": w, "p": p, "f": J, "g": ca.vertcat(*parts)}, lay


# --------------------------------------------------------------------------------------
# Structured derivatives. casadi's own Jacobian/Hessian of the mapped MX graph colour the
# sparsity pattern and push every colour through the whole map (about 10x the work of the
# per-stage SX derivatives for the UR5). We assemble them from per-stage SX blocks instead;
# the compiled library provides them under the names the solver plugins look up.
def stage_blocks(task):
    """SX stage functions (ambient coordinates):

    - ``sdp_jac_f(x, u) -> (df/dx (nx, nx), df/du (nx, nu))``
    - ``sdp_hess_stage(x, u, xi, lam, sigma, mu) -> d^2/d(x,u)^2 [sigma l - lam^T f + mu^T h]``
    - ``sdp_hess_term(x, xi, sigma, mu) -> d^2/dx^2 [sigma l_T + mu^T h]``
    - ``sdp_jac_h(x, xi) -> dh/dx (n_h, nx)``
    """
    nx, nu, n_h = task.nx, task.nu, task.n_h
    x, u, xi = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("xi", task.n_xi)
    lam, sigma, mu = ca.SX.sym("lam", nx), ca.SX.sym("sigma"), ca.SX.sym("mu", n_h)
    z = ca.vertcat(x, u)
    f = task.f_step(x, u)
    h = task.f_state_constraints(x, xi)
    jac_f = ca.Function("sdp_jac_f", [x, u], [ca.jacobian(f, x), ca.jacobian(f, u)])
    lag = sigma * task.f_running_cost(x, u, xi) - ca.dot(lam, f) + (ca.dot(mu, h) if n_h else 0)
    hess_stage = ca.Function("sdp_hess_stage", [x, u, xi, lam, sigma, mu], [ca.hessian(lag, z)[0]])
    lag_T = sigma * task.f_terminal_cost(x, xi) + (ca.dot(mu, h) if n_h else 0)
    hess_term = ca.Function("sdp_hess_term", [x, xi, sigma, mu], [ca.hessian(lag_T, x)[0]])
    jac_h = ca.Function("sdp_jac_h", [x, xi], [ca.jacobian(h, x)])
    return jac_f, hess_stage, hess_term, jac_h


def _pattern(sp: ca.Sparsity) -> np.ndarray:
    """Dense bool mask of a casadi sparsity pattern."""
    return np.array(ca.DM(sp, 1)) != 0


def _assemble(shape, entries):
    """Sparsity + permutation placing value-vector entries at (row, col) in CCS order.

    ``entries``: list of (rows, cols, src) int arrays, src = index into the value vector.
    """
    rows = np.concatenate([e[0].ravel() for e in entries])
    cols = np.concatenate([e[1].ravel() for e in entries])
    src = np.concatenate([e[2].ravel() for e in entries])
    order = np.lexsort((rows, cols))
    rows, cols, src = rows[order], cols[order], src[order]
    colind = np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=shape[1]))])
    return ca.Sparsity(shape[0], shape[1], colind.tolist(), rows.tolist()), src


def nlp_functions(task, nlp: dict, lay: Layout, solver: str, blocks=None) -> list[ca.Function]:
    """The oracle ``nlp`` and every derivative function the ``solver`` plugin looks up in a
    compiled library (``nlp_f``, ``nlp_g``, ``nlp_grad_f``, ``nlp_grad``, ``nlp_jac_g``,
    ``nlp_hess_l``), with the plugin's signatures; gradients by casadi's reverse mode (one
    sweep), Jacobian and Hessian assembled from per-stage SX blocks."""
    T, nx, nu, n_h = lay.T, lay.nx, lay.nu, lay.n_h
    s = nx + nu
    w, p = nlp["x"], nlp["p"]
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", lay.ng)
    f, g = nlp["f"], nlp["g"]
    gamma = lam_f * f + ca.dot(lam_g, g)
    grad_f = ca.gradient(f, w)
    io, iol = ["x", "p"], ["x", "p", "lam_f", "lam_g"]
    funcs = [ca.Function("nlp", [w, p], [f, g], io, ["f", "g"]),
             ca.Function("nlp_f", [w, p], [f], io, ["f"]),
             ca.Function("nlp_g", [w, p], [g], io, ["g"]),
             ca.Function("nlp_grad", [w, p, lam_f, lam_g], [f, g, ca.gradient(gamma, w), ca.gradient(gamma, p)],
                         iol, ["f", "g", "grad_gamma_x", "grad_gamma_p"])]
    if solver == "ipopt":
        funcs.append(ca.Function("nlp_grad_f", [w, p], [f, grad_f], io, ["f", "grad_f_x"]))
    else:
        funcs.append(ca.Function("nlp_grad_f", [w, p], [grad_f], io, ["grad_f_x"]))
    xi = p[nx:]
    XU = ca.reshape(w[: T * s], s, T)
    X, U, xT = XU[:nx, :], XU[nx:, :], w[T * s:]
    xis = ca.repmat(xi, 1, T)
    jac_f, hess_stage, hess_term, jac_h = blocks or stage_blocks(task)
    xidx, uidx = lay.x_index(), lay.u_index()
    gap_i, init_i, h_i = lay.g_index()

    # ---- constraint Jacobian: values [-Fx | -Fu | dh | ones], structural zeros of the blocks dropped
    def block(f, k, row_i, col_i, nblocks, offset):
        """Entries of a mapped block output f_k (r, nblocks c) at rows row_i[b], cols col_i[b]."""
        mask = _pattern(f.sparsity_out(k))
        r, c = mask.shape
        b, i, j = np.meshgrid(np.arange(nblocks), np.arange(r), np.arange(c), indexing="ij")
        keep = mask[i, j]
        b, i, j = b[keep], i[keep], j[keep]
        return row_i[b, i], col_i[b, j], offset + (b * c + j) * r + i

    Fx, Fu = jac_f.map(T)(X, U)  # (nx, T nx), (nx, T nu)
    parts = [-ca.vec(ca.densify(Fx)), -ca.vec(ca.densify(Fu))]
    ent = [block(jac_f, 0, gap_i, xidx[:-1], T, 0), block(jac_f, 1, gap_i, uidx, T, T * nx * nx)]
    off = T * nx * (nx + nu)
    if n_h:
        Xn = ca.horzcat(X[:, 1:], xT)
        parts.append(ca.vec(ca.densify(jac_h.map(T)(Xn, xis))))  # (n_h, T nx) at x_1..x_T
        ent.append(block(jac_h, 0, h_i, xidx[1:], T, off))
        off += T * n_h * nx
    parts.append(ca.MX.ones(T * nx + nx))
    ent.append((gap_i, xidx[1:], off + np.arange(T * nx).reshape(T, nx)))
    ent.append((init_i, xidx[0], off + T * nx + np.arange(nx)))
    sp, src = _assemble((lay.ng, lay.nw), ent)
    jac = ca.MX(sp, ca.vertcat(*parts)[src.tolist()])
    funcs.append(ca.Function("nlp_jac_g", [w, p], [g, jac], io, ["g", "jac_g_x"]))

    # ---- Lagrangian Hessian: block diagonal, blocks (x_t, u_t) and x_T
    lam_gap = ca.reshape(lam_g[gap_i.ravel().tolist()], nx, T)
    mu = ca.reshape(lam_g[h_i.ravel().tolist()], n_h, T) if n_h else ca.MX(0, T)
    mu_stage = ca.horzcat(ca.MX.zeros(n_h, 1), mu[:, : T - 1]) if n_h else ca.MX(0, T)
    Hs = hess_stage.map(T)(X, U, xis, lam_gap, ca.repmat(lam_f, 1, T), mu_stage)  # (s, T s)
    HT = hess_term(xT, xi, lam_f, mu[:, T - 1] if n_h else ca.MX(0, 1))
    vals = ca.vertcat(ca.vec(ca.densify(Hs)), ca.vec(ca.densify(HT)))
    triu = solver == "ipopt"

    def diag_blocks(f, n, start, nblocks, offset):
        mask = _pattern(f.sparsity_out(0)) | _pattern(f.sparsity_out(0)).T
        b, i, j = np.meshgrid(np.arange(nblocks), np.arange(n), np.arange(n), indexing="ij")
        keep = mask[i, j] & ((i <= j) if triu else True)
        b, i, j = b[keep], i[keep], j[keep]
        return start + b * n + i, start + b * n + j, offset + (b * n + j) * n + i

    sp, src = _assemble((lay.nw, lay.nw), [diag_blocks(hess_stage, s, 0, T, 0),
                                           diag_blocks(hess_term, nx, T * s, 1, T * s * s)])
    hess = ca.MX(sp, vals[src.tolist()])
    if triu:
        funcs.append(ca.Function("nlp_hess_l", [w, p, lam_f, lam_g], [hess], iol, ["triu_hess_gamma_x_x"]))
    else:
        funcs.append(ca.Function("nlp_hess_l", [w, p, lam_f, lam_g], [ca.gradient(gamma, w), hess], iol,
                                 ["grad_gamma_x", "hess_gamma_x_x"]))
    return funcs

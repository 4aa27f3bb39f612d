"""Trajectory optimization of OCP (1) with casadi, and verified feedback gains.

    from sdp_cli.trajopt import get_solver, SolveResult
    solver = get_solver(task, max_iter=1000)          # built once per (task, horizon, options)
    res = solver.solve(xi, X_init, U_init)            # x0 = task.initial_state(xi)
    res = solver.solve_from(x0, xi, X_init, U_init)   # explicit x0 (any horizon: get_solver(task, horizon=H))

``res.K (T, nu, ndx)`` are the feedback gains du_t/dx_t, ``res.A, res.B`` the tangent-space
dynamics Jacobians and ``res.Phi = A + B K`` the closed-loop dx_{t+1}/dx_t.

TO families (``--to``): ``ms`` (ours: multiple shooting, fatrop; :func:`get_solver`) and ``ddp`` (the paper's:
box-FDDP, :mod:`sdp_cli.trajopt.ddp`); :func:`get_to_solver` returns either with the same ``solve`` API.
"""

from sdp_cli.families import DEFAULT_TO, TO_FAMILIES
from sdp_cli.trajopt.solver import (DEFAULT_MAX_ITER, DEFAULT_SOLVER, SOLVERS, SolveResult, TrajOptSolver,
                                    build_count, get_solver)
from sdp_cli.errors import SdpError



def check_to(to: str) -> None:
    """One clear error for an unknown family (before any work); every family solves every task."""
    if to not in TO_FAMILIES:
        raise SdpError(f"--to must be one of {', '.join(TO_FAMILIES)}; got {to!r}")


def get_to_solver(task, to: str = DEFAULT_TO, max_iter: int = DEFAULT_MAX_ITER):
    """The solver of TO family ``to`` for ``task`` (cached per process)."""
    check_to(to)
    if to == "ddp":
        from sdp_cli.trajopt.ddp import get_ddp_solver

        return get_ddp_solver(task, max_iter=max_iter)
    return get_solver(task, max_iter=max_iter)


__all__ = ["get_to_solver", "check_to", "TO_FAMILIES", "get_solver", "SolveResult", "TrajOptSolver", "SOLVERS", "DEFAULT_SOLVER", "DEFAULT_MAX_ITER",
           "build_count"]

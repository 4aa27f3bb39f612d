"""Trajectory optimization of OCP (1) with casadi, and verified feedback gains.

    from sdp_cli.trajopt import get_solver, SolveResult
    solver = get_solver(task, max_iter=1000)          # built once per (task, horizon, options)
    res = solver.solve(xi, X_init, U_init)            # x0 = task.initial_state(xi)
    res = solver.solve_from(x0, xi, X_init, U_init)   # explicit x0 (any horizon: get_solver(task, horizon=H))

``res.K (T, nu, ndx)`` are the feedback gains du_t/dx_t, ``res.A, res.B`` the tangent-space
dynamics Jacobians and ``res.Phi = A + B K`` the closed-loop dx_{t+1}/dx_t.
"""

from sdp_cli.trajopt.solver import (DEFAULT_MAX_ITER, DEFAULT_SOLVER, SOLVERS, SolveResult, TrajOptSolver,
                                    build_count, get_solver)

__all__ = ["get_solver", "SolveResult", "TrajOptSolver", "SOLVERS", "DEFAULT_SOLVER", "DEFAULT_MAX_ITER",
           "build_count"]

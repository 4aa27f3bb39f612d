"""Our optimizer against crocoddyl on the same OCP instances, side by side in one process.

    # crocoddyl brings its own pinocchio: run this in a separate environment (docs/benchmarks.md)
    python bench/crocoddyl_compare.py [--tasks pendulum,double_pendulum,ur5-fixed,quadrotor-0] [--n 10] [--repeats 3]

For every task crocoddyl can express (the pendulums and UR5: full actuation, box-bounded torques, no
state constraints; quadrotor-0, whose floor and ceiling are left out and checked on the solutions afterwards:
BoxFDDP has no state constraints, so the quadrotors with columns are not expressible), the OCP of
``sdp_cli.tasks`` is rebuilt with crocoddyl's residual models on the *same* Pinocchio model object (the
quadrotor's: a copy with seven frames added, which changes no dynamics):

- dynamics: ``DifferentialActionModelFreeFwdDynamics`` + ``IntegratedActionModelEuler`` (semi-implicit
  Euler, our ``Task.f_step``; checked: both roll the same controls out to the same states);
- costs: ``1/2 sum_i w_i ||r_i||^2`` residuals, running costs multiplied by dt by the Euler model;
  pendulums: frame translation (10) and control (0.1), terminal frame translation (10);
  UR5 (results version 2): state (q 1e-4, v 0.3), control around gravity compensation (1e-4,
  ``ResidualModelControlGrav``) and frame translation (300), terminal frame translation (100), frame
  velocity in LOCAL_WORLD_ALIGNED (100) and state (1e-4);
  quadrotor-0: ``ActuationModelFloatingBaseThrusters`` with four thrusters placed and turning as ``ALLOC``
  says; our rotation residual ``r = 2 (qx, qy, qz)`` is not crocoddyl's log3, but six frames at ``+-e_i`` on
  the base reproduce it exactly: ``sum_(+-, i) |p_frame - (p_goal +- e_i)|^2 = 6 |e|^2 + 4 |r|^2``
  (``|R - I|_F^2 = 8 sin^2(theta/2)``, ``|q_vec|^2 = sin^2(theta/2)``), so each of the six gets a quarter of the
  rotation weight and the base's translation weight drops by 1.5x the rotation weight; the velocity term a
  ``ResidualModelState`` weighted on v only, the thrusts around hover a ``ResidualModelControl``;
- control bounds: the task's ``u_lb``/``u_ub`` (BoxFDDP; BoxDDP is also timed).

Each instance (collection seed 0, index i) is solved from the task's naive guess by our fatrop
multiple shooting (``get_solver``, tolerance 1e-6, gains off) and by crocoddyl (max 1000 iterations,
threshold 1e-9 on the stopping criterion); the cost of each solution is evaluated by *our* cost function
(so both are measured by the same yardstick), and the best of ``--repeats`` times is kept: process CPU time
(one thread on every side), so that the ratios hold on a loaded machine.
Prints one row per task and solver and the time ratio ours / crocoddyl.

``--exchange IN OUT`` is bench/aligator_compare.py's crocoddyl side (:func:`exchange`).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def quadrotor_model(task):
    """A copy of the quadrotor's model with a frame at the base (``sdp_base``) and six at ``+-e_i`` on it."""
    import pinocchio as pin

    model = pin.Model(task.model)
    joint = model.getJointId("root_joint")
    names = {}
    for name, p in [("sdp_base", np.zeros(3))] + [(f"sdp_{sign}{i}", s * np.eye(3)[i])
                                                   for i in range(3) for sign, s in (("p", 1.0), ("m", -1.0))]:
        names[name] = (model.addFrame(pin.Frame(name, joint, 0, pin.SE3(np.eye(3), p), pin.FrameType.OP_FRAME)), p)
    return model, names


def quadrotor_actuation(state):
    """Four thrusters at ``ALLOC``'s rotor positions, clockwise where ``ALLOC``'s yaw torque is positive."""
    import crocoddyl
    import pinocchio as pin

    from sdp_cli.tasks.quadrotor import ALLOC, C_TAU

    thrusters = []
    for j in range(ALLOC.shape[1]):
        p = np.array([-ALLOC[4, j], ALLOC[3, j], 0.0])      # torque p x (0, 0, f) = (p_y f, -p_x f, 0)
        kind = crocoddyl.ThrusterType.CW if ALLOC[5, j] > 0 else crocoddyl.ThrusterType.CCW
        thrusters.append(crocoddyl.Thruster(pin.SE3(np.eye(3), p), C_TAU, kind))
    act = crocoddyl.ActuationModelFloatingBaseThrusters(state, thrusters)
    assert np.allclose(act.Wthrust, ALLOC, atol=1e-15), "thruster placement does not reproduce ALLOC"
    return act, thrusters


def croc_problem(task, xi):
    import crocoddyl
    import pinocchio as pin

    quadrotor = task.name.startswith("quadrotor")
    if quadrotor:
        if task.n_obstacles:
            raise SystemExit(f"crocoddyl cannot express {task.name!r} here (column constraints)")
        model, frames = quadrotor_model(task)
        state = crocoddyl.StateMultibody(model)
        act, thrusters = quadrotor_actuation(state)
    else:
        state = crocoddyl.StateMultibody(task.model)
        act, thrusters = crocoddyl.ActuationModelFull(state), []
    nu = act.nu
    run, term = crocoddyl.CostModelSum(state, nu), crocoddyl.CostModelSum(state, nu)

    keep = [state, act, run, term, thrusters]   # crocoddyl's bindings do not keep argument objects alive: we do

    def quad(residual, weights=None):
        a = (crocoddyl.ActivationModelQuad(residual.nr) if weights is None
             else crocoddyl.ActivationModelWeightedQuad(np.asarray(weights, dtype=float)))
        c = crocoddyl.CostModelResidual(state, a, residual)
        keep.extend([residual, a, c])
        return c

    if task.name in ("pendulum", "double_pendulum"):
        from sdp_cli.tasks.pendulum import W_GOAL, W_GOAL_T, W_U

        goal = crocoddyl.ResidualModelFrameTranslation(state, task.tip, task.goal, nu)
        run.addCost("goal", quad(goal), W_GOAL)
        run.addCost("u", quad(crocoddyl.ResidualModelControl(state, nu)), W_U)
        term.addCost("goal", quad(crocoddyl.ResidualModelFrameTranslation(state, task.tip, task.goal, nu)), W_GOAL_T)
    elif task.name.startswith("ur5"):
        from sdp_cli.tasks.ur5 import W_EE, W_EE_T, W_Q, W_TWIST_T, W_U, W_V, W_X_T

        x_ref = np.zeros(state.nx)
        run.addCost("x", quad(crocoddyl.ResidualModelState(state, x_ref, nu), [W_Q] * task.nq + [W_V] * task.nv), 1.0)
        run.addCost("u", quad(crocoddyl.ResidualModelControlGrav(state, nu)), W_U)   # u - g(q)
        run.addCost("ee", quad(crocoddyl.ResidualModelFrameTranslation(state, task.ee, task.target(xi), nu)), W_EE)
        term.addCost("ee", quad(crocoddyl.ResidualModelFrameTranslation(state, task.ee, task.target(xi), nu)), W_EE_T)
        term.addCost("twist", quad(crocoddyl.ResidualModelFrameVelocity(state, task.ee, pin.Motion.Zero(),
                                                                       pin.LOCAL_WORLD_ALIGNED, nu)), W_TWIST_T)
        term.addCost("x", quad(crocoddyl.ResidualModelState(state, x_ref, nu)), W_X_T)
    elif quadrotor:
        from sdp_cli.tasks.quadrotor import W_P, W_P_ARRIVE, W_ROT, W_TERMINAL, W_U, W_V, W_V_ARRIVE

        goal = task.target(xi)
        x_ref = np.concatenate([pin.neutral(state.pinocchio), np.zeros(state.nv)])

        def state_costs(cost, scale, w_p_extra=0.0, w_v_extra=0.0):
            base, _ = frames["sdp_base"]
            cost.addCost("p", quad(crocoddyl.ResidualModelFrameTranslation(state, base, goal, nu)),
                         scale * (W_P - 1.5 * W_ROT) + w_p_extra)
            for name, (fid, p) in frames.items():
                if name != "sdp_base":
                    cost.addCost(name, quad(crocoddyl.ResidualModelFrameTranslation(state, fid, goal + p, nu)),
                                 scale * W_ROT / 4)
            cost.addCost("v", quad(crocoddyl.ResidualModelState(state, x_ref, nu), [0.0] * state.nv + [1.0] * state.nv),
                         scale * W_V + w_v_extra)

        state_costs(run, 1.0)
        run.addCost("u", quad(crocoddyl.ResidualModelControl(state, np.asarray(task.u_hover, dtype=float))), W_U)
        arrive = getattr(task, "arrival", False)
        state_costs(term, W_TERMINAL, W_P_ARRIVE if arrive else 0.0, W_V_ARRIVE if arrive else 0.0)
    else:
        raise SystemExit(f"crocoddyl cannot express {task.name!r} here (state constraints)")
    dam_run = crocoddyl.DifferentialActionModelFreeFwdDynamics(state, act, run)
    dam_term = crocoddyl.DifferentialActionModelFreeFwdDynamics(state, act, term)
    running = crocoddyl.IntegratedActionModelEuler(dam_run, task.dt)
    running.u_lb, running.u_ub = task.u_lb.astype(float), task.u_ub.astype(float)
    terminal = crocoddyl.IntegratedActionModelEuler(dam_term, 0.0)
    problem = crocoddyl.ShootingProblem(task.initial_state(xi), [running] * task.T, terminal)
    problem.nthreads = 1   # one thread, as our solver and every sdp process
    _KEEP.append(keep + [dam_run, dam_term, running, terminal, problem])
    return problem


_KEEP: list = []


def check_same_dynamics(task, xi) -> float:
    """Max state difference between crocoddyl's and our rollout of random bounded controls."""
    problem = croc_problem(task, xi)
    rng = np.random.default_rng(0)
    U = rng.uniform(task.u_lb, task.u_ub, (task.T, task.nu)) * 0.2
    xs = problem.rollout(list(U))
    X = task.simulate(task.initial_state(xi), U)
    return float(np.max(np.abs(np.array(xs) - X)))


def check_same_cost(task, xi) -> float:
    """Relative difference of crocoddyl's and our cost on the same trajectory (the naive guess rolled out)."""
    problem = croc_problem(task, xi)
    _, U = task.naive_guess(xi)
    X = task.simulate(task.initial_state(xi), U)
    c = problem.calc(list(X), list(U))
    ours = task.cost(X, U, xi)
    return float(abs(c - ours) / max(1.0, abs(ours)))


def solve_croc(task, xi, kind: str, max_iter: int = 1000):
    import crocoddyl

    problem = croc_problem(task, xi)
    solver = {"BoxFDDP": crocoddyl.SolverBoxFDDP, "BoxDDP": crocoddyl.SolverBoxDDP}[kind](problem)
    _KEEP.append(solver)
    solver.th_stop = 1e-9
    X0, U0 = task.naive_guess(xi)
    t0 = time.process_time()
    ok = solver.solve(list(X0), list(U0), max_iter, False)
    wall = time.process_time() - t0
    return np.array(solver.xs), np.array(solver.us), bool(ok), int(solver.iter), wall


def stop_measure(task, xi, X, U) -> float:
    """crocoddyl 3.x's stopping measure at ``(X, U)``: ``|d1 + d2/2|``, the expected decrease of a full step
    (one backward pass at that point, as its solve computes before testing ``th_stop``)."""
    import crocoddyl

    problem = croc_problem(task, xi)
    solver = crocoddyl.SolverBoxFDDP(problem)
    _KEEP.append(solver)
    solver.setCandidate(list(np.asarray(X, dtype=float)), list(np.asarray(U, dtype=float)), True)
    solver.computeDirection(True)
    solver.updateExpectedImprovement()
    d = solver.expectedImprovement()
    return float(abs(d[0] + 0.5 * d[1]))


def exchange(inp: str, out: str) -> None:
    """bench/aligator_compare.py's crocoddyl side: BoxFDDP from each start of ``inp`` (JSON: task, xis, starts
    [[X, U], ...], max_iter), its measure at each start, process CPU time per solve; written to ``out``."""
    import json

    from sdp_cli.tasks import get_task

    job = json.loads(Path(inp).read_text())
    task = get_task(job["task"])
    rows = []
    for xi, (X0, U0) in zip(job["xis"], job["starts"]):
        xi = np.asarray(xi)
        problem = croc_problem(task, xi)
        import crocoddyl

        solver = crocoddyl.SolverBoxFDDP(problem)
        _KEEP.append(solver)
        solver.th_stop = 1e-9
        t0 = time.process_time()
        ok = solver.solve([np.asarray(x, dtype=float) for x in X0], [np.asarray(u, dtype=float) for u in U0],
                          int(job["max_iter"]), False)
        cpu = time.process_time() - t0
        rows.append({"converged": bool(ok), "iterations": int(solver.iter), "time": cpu,
                     "X": np.array(solver.xs).tolist(), "U": np.array(solver.us).tolist(),
                     "stop_at_start": stop_measure(task, xi, X0, U0)})
    Path(out).write_text(json.dumps({"rows": rows}))


def ddp_rows(task, name, n, repeats, batch, DDPSolver, sample_xi) -> list[dict]:
    """Our box-FDDP (sdp_cli/trajopt/ddp.py, its default Hessian model) on the same instances: in batches of
    ``batch`` (the pipeline's; time per instance = the batch's CPU time / its size) and each instance alone
    (best of ``repeats``); gains off, as crocoddyl's solve has none."""
    solver = DDPSolver(task)
    xis = np.array([sample_xi(task, 0, i) for i in range(n)])
    g = [task.naive_guess(x) for x in xis]
    x0, X0, U0 = (np.array([task.initial_state(x) for x in xis]), np.array([a for a, _ in g]),
                  np.array([b for _, b in g]))
    for j in range(0, n, batch):   # untimed first: builds the compiled maps of every active-set size it meets
        solver.solve_batch(x0[j:j + batch], xis[j:j + batch], X0[j:j + batch], U0[j:j + batch], gains=False)
    solver.solve_batch(x0[:1], xis[:1], X0[:1], U0[:1], gains=False)
    rows = []
    for j in range(0, n, batch):
        sl = slice(j, j + batch)
        best, res = None, None
        for _ in range(repeats):
            t0 = time.process_time()
            res = solver.solve_batch(x0[sl], xis[sl], X0[sl], U0[sl], gains=False)
            wall = time.process_time() - t0
            best = wall if best is None else min(best, wall)
        for k, r in enumerate(res):
            rows.append({"task": name, "solver": f"ours (box-FDDP, batch of {batch})", "i": j + k, "ok": r.converged,
                         "cost": task.cost(r.X, r.U, xis[j + k]), "iterations": r.iterations,
                         "time": best / len(res)})
    for i in range(n):
        best = None
        for _ in range(repeats):
            t0 = time.process_time()
            r = solver.solve_from(x0[i], xis[i], X0[i], U0[i], gains=False)
            wall = time.process_time() - t0
            best = wall if best is None else min(best, wall)
        rows.append({"task": name, "solver": "ours (box-FDDP, alone)", "i": i, "ok": r.converged,
                     "cost": task.cost(r.X, r.U, xis[i]), "iterations": r.iterations, "time": best})
    return rows


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--exchange":
        exchange(sys.argv[2], sys.argv[3])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="pendulum,double_pendulum,ur5-fixed")
    ap.add_argument("--n", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ddp-batch", type=int, default=16, help="our box-FDDP's batch (the pipeline's: 16)")
    ap.add_argument("--ddp-stop", default="ours", help="our box-FDDP's stopping measure: ours or crocoddyl "
                    "(|d1 + d2/2| <= 1e-9, crocoddyl 3.x's rule: iterations under one rule)")
    a = ap.parse_args()
    if "SDP_SOLVE_TIMEOUT" not in os.environ:   # fatrop in this process, so that its CPU time is this process's
        os.environ["SDP_SOLVE_TIMEOUT"] = "0"
        print("SDP_SOLVE_TIMEOUT=0: fatrop solves in this process (unguarded), timed in its CPU time")
    import crocoddyl
    import pandas as pd
    import pinocchio as pin

    from sdp_cli.algorithm.collect import sample_xi
    from sdp_cli.tasks import get_task
    from sdp_cli.trajopt import get_solver

    print(f"crocoddyl {crocoddyl.__version__}, pinocchio {pin.__version__}, {platform.machine()}, "
          f"python {platform.python_version()}; n = {a.n} instances per task, best of {a.repeats} runs")
    from sdp_cli.trajopt.ddp import DDPSolver

    rows = []
    for name in a.tasks.split(","):
        task = get_task(name)
        ours = get_solver(task, max_iter=1000)
        rows += ddp_rows(task, name, a.n, a.repeats, a.ddp_batch, lambda t: DDPSolver(t, stop_rule=a.ddp_stop), sample_xi)
        print(f"{name}: dynamics check, max |x_croc - x_ours| = {check_same_dynamics(task, sample_xi(task, 0, 0)):.2e}; "
              f"cost check, relative |cost_croc - cost_ours| = {check_same_cost(task, sample_xi(task, 0, 0)):.2e}")
        for i in range(a.n):
            xi = sample_xi(task, 0, i)
            X0, U0 = task.naive_guess(xi)
            best = None
            for _ in range(a.repeats):
                t0 = time.process_time()
                r = ours.solve(xi, X0, U0, gains=False)
                cpu = time.process_time() - t0
                best = cpu if best is None else min(best, cpu)
            rows.append({"task": name, "solver": "ours (fatrop, multiple shooting)", "i": i, "ok": r.converged,
                         "cost": task.cost(r.X, r.U, xi), "iterations": r.iterations, "time": best})
            for kind in ("BoxFDDP", "BoxDDP"):
                best = None
                for _ in range(a.repeats):
                    X, U, ok, it, wall = solve_croc(task, xi, kind)
                    best = wall if best is None else min(best, wall)
                viol = max(float(np.max(U - task.u_ub, initial=0)), float(np.max(task.u_lb - U, initial=0)),
                           task.constraint_violation(X, U, xi))   # (the quadrotor's floor and ceiling, unmodelled)
                rows.append({"task": name, "solver": f"crocoddyl {kind}", "i": i, "ok": ok and viol <= 1e-6,
                             "cost": task.cost(X, U, xi), "iterations": it, "time": best})
    df = pd.DataFrame(rows)
    ours_cost = df[df.solver == "ours (fatrop, multiple shooting)"].set_index(["task", "i"]).cost
    df["cost_vs_ours"] = [c - ours_cost[(t, i)] for t, i, c in zip(df.task, df.i, df.cost)]
    agg = df.groupby(["task", "solver"], sort=False).agg(
        converged=("ok", "mean"), cost_mean=("cost", "mean"), cost_median=("cost", "median"),
        lower_cost_than_ours=("cost_vs_ours", lambda s: int((s < -1e-6).sum())),
        iterations=("iterations", "mean"), iterations_median=("iterations", "median"),
        time_ms_mean=("time", lambda s: 1e3 * s.mean()),
        time_ms_median=("time", lambda s: 1e3 * s.median()))
    print(agg.to_string(float_format=lambda v: f"{v:.4g}"))
    for name in a.tasks.split(","):
        t = agg.loc[name]
        for ours_name in [s for s in t.index if s.startswith("ours")]:
            o = t.loc[ours_name, "time_ms_median"]
            for kind in ("BoxFDDP", "BoxDDP"):
                c = t.loc[f"crocoddyl {kind}", "time_ms_median"]
                print(f"{name}: median time {ours_name} / crocoddyl {kind} = {o / c:.2f} "
                      f"({'ours faster' if o < c else 'crocoddyl faster'})")
        same = df[(df.task == name) & (df.solver == f"ours (box-FDDP, batch of {a.ddp_batch})")].set_index("i")
        croc = df[(df.task == name) & (df.solver == "crocoddyl BoxFDDP")].set_index("i")
        both = same.ok & croc.ok
        rel = (same.cost - croc.cost).abs() / croc.cost.abs()
        print(f"{name}: our box-FDDP and crocoddyl BoxFDDP both converged on {int(both.sum())} of {len(both)}, at the same "
              f"optimum (relative cost difference <= 1e-6) on {int((both & (rel <= 1e-6)).sum())}; ours lower on "
              f"{int((both & (same.cost < croc.cost) & (rel > 1e-6)).sum())}, higher on "
              f"{int((both & (same.cost > croc.cost) & (rel > 1e-6)).sum())}")
        it = t.loc["crocoddyl BoxFDDP", "iterations_median"]
        for ours_name in [s for s in t.index if s.startswith("ours (box-FDDP")]:
            print(f"{name}: median iterations {ours_name} / crocoddyl BoxFDDP = "
                  f"{t.loc[ours_name, 'iterations_median'] / it:.2f}")


if __name__ == "__main__":
    main()

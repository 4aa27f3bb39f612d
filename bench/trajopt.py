"""Benchmark of the trajectory optimizer: speed, robustness, gain accuracy.

Per task and solver (fatrop, ipopt) it prints the one-off build time (first build in this
process, which compiles the NLP into the JIT cache unless it is already there, and a rebuild
that loads the cached library), cold-start solves from ``task.naive_guess`` over ``--n``
random xi (seeded): mean/median solve time, mean iterations, convergence rate, mean cost of
the converged ones; and the finite-difference error of the feedback gains (median relative
error of ``du_t`` vs ``K_t delta`` at steps with no control at a bound ("free") and at steps
with a clamped control ("clamped"), see :mod:`sdp_cli.trajopt.verify`).

With ``|u| <= 25`` the pendulum tasks never touch their bounds, so ``--tight U`` adds a
variant of each pendulum task with ``|u| <= U`` (default 1.0) to measure the gains at clamped steps.

A task label ``NAME@T100`` runs task NAME on horizon 100 (``get_task(NAME, T=100)``), e.g.
``ur5-fixed@T100`` for the "UR5 reach with T=100" speed reference. The "viol" column is the
max constraint violation (dynamics gaps, x0, control bounds, state constraints) over all solves.

    python bench/trajopt.py                       # every task variant (DEFAULT_TASKS)
    python bench/trajopt.py --tasks ur5-fixed,quadrotor-1 --n 5 --fd-instances 1
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time

import numpy as np

from sdp_cli.tasks import get_task
from sdp_cli.trajopt import TrajOptSolver, get_solver
from sdp_cli.trajopt.verify import check_dynamics_jacobians, check_gains


#: every registered task variant (the alias ``quadrotor`` = quadrotor-0 is left out) + UR5 on T = 100
DEFAULT_TASKS = ("pendulum,double_pendulum,ur5-fixed,ur5-rinit,ur5-rtgt,ur5-rinit-rtgt,ur5-fixed@T100,"
                 "ur5-rinit-rtgt@T100,quadrotor-0,quadrotor-1,quadrotor-3,quadrotor-9")
#: tasks whose bounds are never active, so that ``--tight`` adds a clamped variant
TIGHT_TASKS = ("pendulum", "double_pendulum")


def task_from_label(label: str):
    """``NAME`` or ``NAME@T<horizon>`` -> task instance."""
    name, _, hor = label.partition("@T")
    return get_task(name, T=int(hor)) if hor else get_task(name)


def tight_variant(name: str, u_max: float):
    """A copy of task ``name`` with control bounds clipped to ``[-u_max, u_max]``."""
    task = copy.copy(get_task(name))
    task.u_lb = np.maximum(task.u_lb, -u_max)
    task.u_ub = np.minimum(task.u_ub, u_max)
    return task


def gain_errors(task, results, n_inst: int, n_steps: int, seed: int, eps: float):
    """Median FD relative errors at free and clamped steps over ``n_inst`` converged results."""
    rng = np.random.default_rng(seed)
    free, clamped, clamped_fd, dyn = [], [], [], []
    for res in [r for r in results if r.converged][:n_inst]:
        is_cl = res.clamped.any(1)
        f_steps = np.flatnonzero(~is_cl)
        c_steps = np.flatnonzero(is_cl)
        pick = lambda s: rng.choice(s, min(n_steps, len(s)), replace=False) if len(s) else []  # noqa: E731
        steps_f, steps_c = pick(f_steps), pick(c_steps)
        for c in check_gains(task, res, steps_f, eps=eps, seed=int(rng.integers(1 << 30))):
            free.append(c.rel_error)
        for c in check_gains(task, res, steps_c, eps=eps, seed=int(rng.integers(1 << 30))):
            clamped.append(c.rel_error)
            clamped_fd.append(c.clamped_fd)
        dyn.append(max(check_dynamics_jacobians(task, res, list(steps_f[:2]) + list(steps_c[:1]))))
    med = lambda v: float(np.nanmedian(v)) if len(v) and not np.all(np.isnan(v)) else float("nan")  # noqa: E731
    return (med(free), len(free), med(clamped), len(clamped), max(clamped_fd, default=float("nan")),
            max(dyn, default=float("nan")))


def run(task, label: str, solver: str, args) -> dict:
    t0 = time.perf_counter()
    s = get_solver(task, solver=solver, max_iter=args.max_iter)
    build_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    TrajOptSolver(task, task.T, solver, args.max_iter, s.tol, s.viol_tol, s.jitted)
    build_cached = time.perf_counter() - t0
    rng = np.random.default_rng(args.seed)
    results = []
    for _ in range(args.n):
        xi = task.sample_xi(rng)
        results.append(s.solve(xi, *task.naive_guess(xi)))
    times = np.array([r.solve_time for r in results])
    conv = np.array([r.converged for r in results])
    row = {"task": label, "solver": solver, "jit": s.jitted, "build_first": build_first,
           "build_cached": build_cached, "mean": times.mean(), "median": np.median(times),
           "iters": np.mean([r.iterations for r in results]), "conv": conv.mean(),
           "cost": np.mean([r.cost for r in results if r.converged]) if conv.any() else float("nan"),
           "gain_t": np.median([r.gain_time for r in results]),
           "clamped_frac": np.mean([r.clamped.any(1).mean() for r in results]),
           "viol": max(r.max_violation for r in results)}
    fails = sorted({r.status for r in results if not r.converged})
    if fails:
        row["fails"] = fails
    if args.fd_instances:
        (row["fd_free"], row["n_free"], row["fd_clamped"], row["n_clamped"], row["clamped_du"],
         row["dyn_err"]) = gain_errors(task, results, args.fd_instances, args.fd_steps, args.seed, args.eps)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default=DEFAULT_TASKS, help="comma-separated task labels (NAME or NAME@T<horizon>)")
    p.add_argument("--solvers", default="fatrop,ipopt")
    p.add_argument("--n", type=int, default=20, help="random xi per task (cold starts)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-iter", type=int, default=1000)
    p.add_argument("--tight", type=float, default=1.0, help="also run |u| <= TIGHT variants (0: off)")
    p.add_argument("--fd-instances", type=int, default=3, help="converged instances per row for the gain FD check")
    p.add_argument("--fd-steps", type=int, default=4, help="free and clamped steps checked per instance")
    p.add_argument("--eps", type=float, default=1e-4, help="FD state perturbation norm")
    args = p.parse_args(argv)

    print(f"# sdp trajopt bench: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, "
          f"SDP_CACHE_DIR={os.environ.get('SDP_CACHE_DIR', '~/.cache/sdp')}", flush=True)
    print("# " + " | ".join(HEADER), flush=True)
    rows = []
    for name in [t for t in args.tasks.split(",") if t]:
        variants = [(task_from_label(name), name)]
        if args.tight > 0 and name in TIGHT_TASKS:
            variants.append((tight_variant(name, args.tight), f"{name} |u|<={args.tight:g}"))
        for task, label in variants:
            for solver in args.solvers.split(","):
                row = run(task, label, solver, args)
                rows.append(row)
                print(fmt_row(row), flush=True)
                for f in row.get("fails", []):
                    print(f"    failure: {f}", flush=True)
    print(f"# load average at the end {os.getloadavg()[0]:.2f}")
    print_ratios(rows)
    return 0


HEADER = ("task", "solver", "jit", "build 1st/cached s", "solve mean/med s", "iters", "conv", "viol", "cost",
          "gain s", "FD free med (n)", "FD clamped med (n)", "max|du_clamped|", "A,B err")


def fmt_row(r: dict) -> str:
    fd = (f"{r.get('fd_free', float('nan')):.1e} ({r.get('n_free', 0)})",
          f"{r.get('fd_clamped', float('nan')):.1e} ({r.get('n_clamped', 0)})",
          f"{r.get('clamped_du', float('nan')):.1e}", f"{r.get('dyn_err', float('nan')):.1e}")
    return (f"{r['task']:<26} {r['solver']:<6} {str(r['jit']):<5} {r['build_first']:6.2f}/{r['build_cached']:5.2f}  "
            f"{r['mean']:.4f}/{r['median']:.4f}  {r['iters']:6.1f} {r['conv']:5.0%} {r['viol']:.0e} {r['cost']:9.3f}  "
            f"{r['gain_t']:.4f}  " + "  ".join(fd))


def print_ratios(rows) -> None:
    by = {(r["task"], r["solver"]): r for r in rows}
    for task in dict.fromkeys(r["task"] for r in rows):
        a, b = by.get((task, "ipopt")), by.get((task, "fatrop"))
        if a and b:
            print(f"# {task}: median cold solve ipopt/fatrop = {a['median'] / b['median']:.2f}x, "
                  f"convergence fatrop {b['conv']:.0%} vs ipopt {a['conv']:.0%}")


if __name__ == "__main__":
    sys.exit(main())

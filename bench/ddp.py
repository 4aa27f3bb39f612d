"""Box-FDDP (sdp_cli/trajopt/ddp.py) batched: time per instance against the batch size N and the horizon T,
where the time goes, and the goal (double pendulum <= 20 ms amortized per instance at N = 50 on 1 thread).

    python bench/ddp.py [--task double_pendulum] [--sizes 1,10,50] [--horizons 50,100,200] [--refill 16] [--hessians] [--dense-call] [--array-backward]

Instances: collection seed 0, indices 0..N-1, from the naive guess; the compiled functions are built (and
cached) before timing. Prints per (T, N): converged, mean / max iterations, batch wall time, amortized ms per
instance and per instance-iteration; then a profile of the N = max, T = task default batch by phase. With
``--refill W``: the N = max instances solved as batches of W in turn against one call that keeps W iterating and
starts the next instance as one finishes (``solve_batch(width=W)``), in process CPU time, round-robin over
``--repeats``, with a check that every instance's solution is the same both ways. With ``--hessians``: the
N = max instances from the naive guess under the iterations' Hessian model before issue "Our box-FDDP within 2x"
(``hessian="exact"``), the PSD-projected one (``"psd"``) and, on a task that declares residuals (UR5), the
Gauss-Newton one (``"gn"``, the default there): converged, iterations, CPU time, and how often the optimum
changed (relative cost difference > 1e-6), with the cost distribution of each. With ``--dense-call``: the
N = max instances with the compiled maps called as casadi calls whose outputs go through ``np.asarray`` (how
maps with structurally sparse outputs were called before they were densified) against the buffer calls
(``ddp_model.DenseCall``), CPU time, round-robin over ``--repeats``, with a check of identical solutions. With
``--array-backward``: the N = max instances with the backward pass and the LQ model as numpy array operations over
the batch (the solver's until 2026-12-07, kept as the oracle in tests/test_ddp_kernels.py) against the compiled ones
(sdp_cli/trajopt/ddp_kernels.py), CPU time, round-robin over ``--repeats``: the ratio, and how far the solutions
and iteration counts of the two are apart.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime
import platform
import pstats
import time

import numpy as np

from sdp_cli.algorithm.solve_jobs import sample_xi
from sdp_cli.tasks import get_task
from sdp_cli.trajopt.ddp import DDPSolver
from sdp_cli.trajopt.ddp_model import gauss_newton


def batch(task, n):
    xis = np.array([sample_xi(task, 0, i) for i in range(n)])
    guesses = [task.naive_guess(x) for x in xis]
    return (np.array([task.initial_state(x) for x in xis]), xis, np.array([g[0] for g in guesses]),
            np.array([g[1] for g in guesses]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="double_pendulum")
    ap.add_argument("--sizes", default="1,10,50")
    ap.add_argument("--horizons", default="50,100,200")
    ap.add_argument("--refill", type=int, default=0, help="compare batches of this width with a refilled batch")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--hessians", action="store_true", help="compare the Hessian models (exact, PSD-projected, Gauss-Newton where the task has residuals)")
    ap.add_argument("--dense-call", action="store_true", help="compare casadi calls through np.asarray with buffers")
    ap.add_argument("--array-backward", action="store_true", help="compare the numpy backward pass and LQ model with the compiled ones")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    sizes = [int(s) for s in a.sizes.split(",")]
    print(f"# bench/ddp.py --task {a.task}, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
          f"{platform.node()} ({platform.machine()}), 1 thread")
    print("| T | N | converged | iterations mean / max | batch wall (s) | ms per instance | ms per instance-iteration |")
    print("|---|---|---|---|---|---|---|")
    for T in [int(h) for h in a.horizons.split(",")]:
        task = get_task(a.task, T=T)
        solver = DDPSolver(task)
        solver.solve_batch(*[v[:1] for v in batch(task, 1)], gains=False)     # build the maps once
        for n in sizes:
            args = batch(task, n)
            t0 = time.perf_counter()
            res = solver.solve_batch(*args, gains=False)
            wall = time.perf_counter() - t0
            it = np.array([r.iterations for r in res])
            print(f"| {T} | {n} | {np.mean([r.converged for r in res]):.0%} | {it.mean():.1f} / {it.max()} | "
                  f"{wall:.2f} | {1000 * wall / n:.1f} | {1000 * wall / max(1, it.sum()):.2f} |", flush=True)
    task = get_task(a.task)
    solver = DDPSolver(task)
    args = batch(task, max(sizes))
    solver.solve_batch(*[v[:1] for v in args], gains=False)
    prof = cProfile.Profile()
    prof.enable()
    solver.solve_batch(*args, gains=False)
    prof.disable()
    st = pstats.Stats(prof)
    total = max(v[3] for v in st.stats.values())
    print(f"\nwhere the time goes (T = {task.T}, N = {max(sizes)}; cumulative seconds, share of the batch):")
    # the box QP runs inside the compiled backward pass (sdp_cli/trajopt/ddp_kernels.py): its time is _backward's
    for name in ("_backward", "_line_search", "_rollout", "_derivatives", "_model"):
        cum = sum(v[3] for k, v in st.stats.items() if k[2] == name)
        print(f"  {name:14s} {cum:7.3f} s  {cum / total:5.1%}")
    if a.refill:
        refill(solver, args, a.refill, a.repeats)
    if a.hessians:
        hessians(task, args)
    if a.dense_call:
        dense_call(task, args, a.repeats)
    if a.array_backward:
        array_backward(task, args, a.repeats)


def array_backward(task, args, repeats: int) -> None:
    """The solve with the backward pass and LQ model of numpy array operations against the compiled ones."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_ddp_kernels import array_backward as numpy_pass, array_model

    solvers = {"numpy": DDPSolver(task), "compiled": DDPSolver(task)}
    old = solvers["numpy"]
    old._backward = lambda d, gaps, U, reg: numpy_pass(task, old.T, old.ndx, d, gaps, U, reg)
    old._model = array_model
    times = {k: [] for k in solvers}
    res = {}
    for s in solvers.values():
        s.solve_batch(*[v[:1] for v in args], gains=False)     # build the maps, compile the kernels
    for _ in range(repeats):
        for k, s in solvers.items():
            t0 = time.process_time()
            res[k] = s.solve_batch(*args, gains=False)
            times[k].append(time.process_time() - t0)
    dx = max(float(np.abs(p.X - q.X).max()) for p, q in zip(res["numpy"], res["compiled"]))
    dit = sum(p.iterations != q.iterations for p, q in zip(res["numpy"], res["compiled"]))
    dc = max(abs(p.cost - q.cost) / abs(p.cost) for p, q in zip(res["numpy"], res["compiled"]))
    a, b = (1000 * np.median(times[k]) / len(args[0]) for k in ("numpy", "compiled"))
    print(f"\nbackward pass and LQ model (N = {len(args[0])}, median of {repeats}, CPU ms per instance): numpy {a:.1f}, "
          f"compiled {b:.1f}, ratio {a / b:.2f}x; largest state difference of the solutions {dx:.1e}, relative cost "
          f"difference {dc:.1e}, iteration counts that differ: {dit} of {len(args[0])}")


class _AsArrayCall:
    """A mapped casadi function called the usual way, its outputs through ``np.asarray`` (C order)."""

    def __init__(self, f):
        self.f = f

    def __call__(self, *args):
        out = self.f(*args)
        return tuple(np.asarray(o) for o in out) if isinstance(out, (tuple, list)) else np.asarray(out)


def dense_call(task, args, repeats: int) -> None:
    """The solve with every compiled map called through ``np.asarray`` against through its buffer."""
    solvers = {"np.asarray": DDPSolver(task), "buffer": DDPSolver(task)}
    slow = solvers["np.asarray"]
    slow._map = lambda name, n: slow._maps.setdefault((name, n), _AsArrayCall(slow._f[name].map(n, "serial")))
    times = {k: [] for k in solvers}
    res = {}
    for s in solvers.values():
        s.solve_batch(*args, gains=False)                # build the maps
    for _ in range(repeats):
        for k, s in solvers.items():
            t0 = time.process_time()
            res[k] = s.solve_batch(*args, gains=False)
            times[k].append(time.process_time() - t0)
    same = all(np.array_equal(p.X, q.X) and p.iterations == q.iterations for p, q in zip(res["np.asarray"], res["buffer"]))
    a, b = (1000 * np.median(times[k]) / len(args[0]) for k in ("np.asarray", "buffer"))
    print(f"\ncasadi outputs (N = {len(args[0])}, median of {repeats}, CPU ms per instance): through np.asarray {a:.1f}, "
          f"through the buffer {b:.1f}, ratio {a / b:.2f}x; same solutions: {same}")


def hessians(task, args) -> None:
    """The exact Hessian model against the PSD-projected one and, where the task declares residuals, the
    Gauss-Newton one, from the naive guess: which optimum each reaches, at what cost."""
    res, cpu = {}, {}
    models = ("exact", "psd", "gn") if gauss_newton(task) else ("exact", "psd")
    for model in models:
        solver = DDPSolver(task, hessian=model)
        solver.solve_batch(*[v[:1] for v in args], gains=False)          # build the maps
        t0 = time.process_time()
        res[model] = solver.solve_batch(*args, gains=False)
        cpu[model] = time.process_time() - t0
    cost = {m: np.array([r.cost for r in res[m]]) for m in models}
    print(f"\nHessian models from the naive guess ({task.name}, N = {len(cost['exact'])}):")
    print("| model | converged | iterations median (min-max) | CPU s (batch) | cost mean | cost median |")
    print("|---|---|---|---|---|---|")
    for m in models:
        it = np.array([r.iterations for r in res[m]])
        print(f"| {m} | {np.mean([r.converged for r in res[m]]):.0%} | {np.median(it):g} ({it.min()}-{it.max()}) | "
              f"{cpu[m]:.2f} | {cost[m].mean():.4g} | {np.median(cost[m]):.4g} |")
    ex = cost["exact"]
    for m in models[1:]:
        both = np.array([a.converged and b.converged for a, b in zip(res["exact"], res[m])])
        rel = (cost[m] - ex) / np.abs(ex)
        moved = both & (np.abs(rel) > 1e-6)
        print(f"{m} against exact: both converged on {both.sum()} of {len(ex)}; the optimum changed (|relative cost "
              f"difference| > 1e-6) on {moved.sum()}: {(moved & (rel < 0)).sum()} lower and {(moved & (rel > 0)).sum()} "
              f"higher under {m}; the others agree to {np.abs(rel[both & ~moved]).max(initial=0):.1e}")


def refill(solver, args, w: int, repeats: int) -> None:
    """Batches of ``w`` in turn against one refilled batch of width ``w`` (process CPU time per instance)."""
    n = len(args[0])
    times = {"batches": [], "refill": []}
    for _ in range(repeats):
        t0 = time.process_time()
        turn = [r for j in range(0, n, w) for r in solver.solve_batch(*[v[j:j + w] for v in args], gains=False)]
        times["batches"].append(time.process_time() - t0)
        t0 = time.process_time()
        filled = solver.solve_batch(*args, gains=False, width=w)
        times["refill"].append(time.process_time() - t0)
    same = all(np.array_equal(p.X, q.X) and np.array_equal(p.U, q.U) and p.iterations == q.iterations
               for p, q in zip(turn, filled))
    b, r = (1000 * np.median(times[k]) / n for k in ("batches", "refill"))
    print(f"\nrefill (N = {n}, width {w}, median of {repeats}, CPU ms per instance): batches of {w} in turn {b:.1f}, "
          f"refilled {r:.1f}, ratio {b / r:.2f}x; same solutions: {same}")


if __name__ == "__main__":
    main()

"""Throughput of ``sdp collect`` on 1 and 2 local workers and on a 2-worker Dask LocalCluster.

    python bench/collect_scaling.py [--task quadrotor-3] [--n-traj 40] [--seed 0] [--repeat 2]

Prints trajectories (kept, converged) per second and solves (attempts) per second for
each executor, the speed-up of 2 workers over 1 and the parallel efficiency
``speed-up / 2``. All runs solve the same indices (same seed) and must give the same
dataset, which is checked. Solvers are built (and JIT-compiled) before timing; the Dask
cluster's start-up is reported separately, its workers are warmed before timing. Each
executor runs ``--repeat`` times (interleaved) and its best wall time counts; the load
average is printed because other processes on the machine skew the ratios.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from sdp_cli.data.artifacts import load_npz
from sdp_cli.algorithm.collect import CollectConfig, collect, warm_solver
from sdp_cli.execution.executor import make_executor


def _run(cfg: CollectConfig, out: Path, **kw) -> tuple[float, int, dict]:
    t0 = time.perf_counter()
    path, stats = collect(cfg, out, **kw)
    wall = time.perf_counter() - t0
    arrays, _ = load_npz(path)
    return wall, stats.attempts, arrays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="quadrotor-3")
    ap.add_argument("--n-traj", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    cfg = CollectConfig(task=args.task, n_traj=args.n_traj, seed=args.seed)
    print(f"task {cfg.task}, {cfg.n_traj} trajectories, seed {cfg.seed}, {os.cpu_count()} cores")
    t0 = time.perf_counter()
    warm_solver(cfg.task, cfg.task_options, cfg.max_iter)  # build + JIT-compile once, not timed below
    print(f"solver build in this process: {time.perf_counter() - t0:.1f} s")

    rows: dict[str, tuple] = {}

    def keep_best(name, res):
        if name not in rows or res[0] < rows[name][0]:
            rows[name] = res

    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="sdp_bench_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        with make_executor("dask", workers=2) as ex:
            ex.warm(warm_solver, cfg.task, cfg.task_options, cfg.max_iter)
            startup = time.perf_counter() - t0
            for r in range(args.repeat):
                keep_best("local, 1 worker", _run(cfg, tmp / f"l1_{r}.npz", workers=1))
                keep_best("local, 2 workers", _run(cfg, tmp / f"l2_{r}.npz", workers=2))
                keep_best("dask LocalCluster, 2 workers", _run(cfg, tmp / f"d2_{r}.npz", executor=ex))
    rows = {k: rows[k] for k in ("local, 1 worker", "local, 2 workers", "dask LocalCluster, 2 workers")}

    ref = rows["local, 1 worker"][2]
    for name, (_, _, arrays) in rows.items():
        assert np.array_equal(arrays["index"], ref["index"]), name
        np.testing.assert_allclose(arrays["X"], ref["X"], atol=1e-8, err_msg=name)
    print(f"dask LocalCluster start-up + worker warm-up: {startup:.1f} s (not in the numbers below)")
    print(f"{'executor':32s} {'wall s':>8s} {'traj/s':>8s} {'solves/s':>9s} {'speed-up':>9s} {'efficiency':>10s}")
    base = cfg.n_traj / rows["local, 1 worker"][0]
    for name, (wall, attempts, _) in rows.items():
        tps = cfg.n_traj / wall
        n_workers = 1 if "1 worker" in name else 2
        print(f"{name:32s} {wall:8.2f} {tps:8.2f} {attempts / wall:9.2f} {tps / base:9.2f}x "
              f"{tps / base / n_workers:10.0%}")
    print(f"identical datasets: yes; load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after "
          f"(best of {args.repeat} runs each)")


if __name__ == "__main__":
    main()

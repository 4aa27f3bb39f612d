"""TO alone on the faithful tasks, every TO baseline, beside the paper's numbers (results/tasks/TO_alone.md).

    python bench/to_alone.py [--tasks pendulum,double_pendulum,...] [--baselines ms-fatrop,ss-ipopt,ddp] [--n 50]
                             [--n-slow 10] [--jobs 2] [--out results/tasks/TO_alone.md [--update]]

Per task and baseline, from the naive guess over the first ``n`` instances of collection seed 0
(``--n-slow`` for the (task, baseline) pairs listed in SLOW): converged %, reached % (the task's
success: end effector / base within ``task.goal_tolerance`` of the goal at T, no constraint
violation above 1e-6, converged), mean and median cost over the converged solves, mean iterations,
mean and median solve time, and the paper's figure where it gives one. Baselines:

- ``ms-fatrop``: our optimizer, multiple shooting solved by fatrop (:mod:`sdp_cli.trajopt.solver`);
- ``ss-ipopt``: single shooting (controls only, states by rollout), IPOPT with a limited-memory Hessian
  (:mod:`sdp_cli.trajopt.single_shooting`);
- ``ddp``: box-FDDP (:mod:`sdp_cli.trajopt.ddp`, the paper's solver family), the ``n`` instances solved as one
  batch; its time per instance is its iterations x the batch's wall time per instance-iteration (the batch's
  wall time / n is printed beside it); the quadrotor's state constraints by its augmented-Lagrangian loop.

``--baselines ddp --update`` re-runs only those pairs and keeps the other rows of ``--out`` (a line under the
header says which rows, at which commit and date).

All with a 1000-iteration cap; tolerance 1e-6 (fatrop, IPOPT), crocoddyl's stopping rule 1e-9 (DDP). Each (task, baseline) runs in its own process
(one thread), ``--jobs`` at a time; times are wall seconds of the solve calls on this machine.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

TASKS = "pendulum,double_pendulum,ur5-fixed,ur5-rinit,quadrotor-0,quadrotor-1,quadrotor-3,quadrotor-9"
BASELINES = ("ms-fatrop", "ss-ipopt", "ddp")
SLOW = {("ur5-fixed", "ss-ipopt"), ("ur5-rinit", "ss-ipopt"), ("quadrotor-0", "ss-ipopt")}
#: pairs not run: single shooting with the quadrotor's column constraints took > 2 min per solve in a probe
SKIP = {("quadrotor-1", "ss-ipopt"), ("quadrotor-3", "ss-ipopt"), ("quadrotor-9", "ss-ipopt")}
#: the paper's TO-alone figures (Sec. IV, Fig. 2b, Sec. IV-E)
PAPER = {"double_pendulum": "mean cost 50.1, 896 iterations, 80% not converged (ProxDDP, Fig. 2b)",
         "quadrotor-9": "16.3 s per solve (Sec. IV-E)"}


def one(task_name: str, baseline: str, n: int) -> dict:
    from sdp_cli.algorithm.collect import sample_xi
    from sdp_cli.tasks import get_task

    task = get_task(task_name)
    if baseline == "ddp":
        return _ddp(task, n)
    if baseline == "ms-fatrop":
        from sdp_cli.trajopt import get_solver

        s = get_solver(task, max_iter=1000)
        solve = lambda xi: s.solve(xi, *task.naive_guess(xi), gains=False)  # noqa: E731
    else:
        from sdp_cli.trajopt.single_shooting import get_single_shooting

        s = get_single_shooting(task, max_iter=1000)
        solve = lambda xi: s.solve(xi, task.naive_guess(xi)[1])  # noqa: E731
    rows = []
    for i in range(n):
        xi = sample_xi(task, 0, i)
        r = solve(xi)
        reached = bool(r.converged and task.goal_distance(r.X[-1], xi) <= task.goal_tolerance
                       and task.constraint_violation(r.X, r.U, xi) <= 1e-6)
        rows.append({"converged": bool(r.converged), "reached": reached, "cost": float(r.cost),
                     "iterations": int(r.iterations), "time": float(r.solve_time)})
    return {"task": task_name, "baseline": baseline, "n": n, "rows": rows}


def _ddp(task, n: int) -> dict:
    from sdp_cli.algorithm.collect import sample_xi
    from sdp_cli.trajopt.ddp import DDPSolver

    xis = np.array([sample_xi(task, 0, i) for i in range(n)])
    guesses = [task.naive_guess(xi) for xi in xis]
    solver = DDPSolver(task, max_iter=1000)
    results = solver.solve_batch(np.array([task.initial_state(x) for x in xis]), xis,
                                 np.array([g[0] for g in guesses]), np.array([g[1] for g in guesses]), gains=False)
    rows = []
    for xi, r in zip(xis, results):
        reached = bool(r.converged and task.goal_distance(r.X[-1], xi) <= task.goal_tolerance
                       and task.constraint_violation(r.X, r.U, xi) <= 1e-6)
        rows.append({"converged": bool(r.converged), "reached": reached, "cost": float(r.cost),
                     "iterations": int(r.iterations), "time": float(r.solve_time)})
    return {"task": task.name, "baseline": "ddp", "n": n, "rows": rows, "batch_wall": results[0].batch_wall_time}


def summarize(res: dict) -> dict:
    rows = res["rows"]
    conv = np.array([r["converged"] for r in rows])
    cost = np.array([r["cost"] for r in rows])[conv]
    t = np.array([r["time"] for r in rows])
    return {"task": res["task"], "baseline": res["baseline"], "n": res["n"], "converged": conv.mean(),
            "reached": np.mean([r["reached"] for r in rows]),
            "cost_mean": cost.mean() if cost.size else float("nan"),
            "cost_median": float(np.median(cost)) if cost.size else float("nan"),
            "iterations": np.mean([r["iterations"] for r in rows]), "time_mean": t.mean(),
            "time_median": float(np.median(t)), "batch_wall": res.get("batch_wall")}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        print(json.dumps(one(sys.argv[2], sys.argv[3], int(sys.argv[4]))))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default=TASKS)
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--n-slow", type=int, default=10)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--baselines", default=",".join(BASELINES))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--update", action="store_true", help="keep the rows of --out of the pairs not run")
    a = ap.parse_args()
    baselines = a.baselines.split(",")
    jobs = [(t, b, a.n_slow if (t, b) in SLOW else a.n) for t in a.tasks.split(",") for b in baselines
            if (t, b) not in SKIP]

    def run(job):
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        r = subprocess.run([sys.executable, __file__, "--one", *map(str, job)], capture_output=True, text=True,
                           env=env)
        if r.returncode != 0:
            raise RuntimeError(f"{job}: {r.stderr[-1500:]}")
        return summarize(json.loads(r.stdout.strip().splitlines()[-1]))

    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(run, jobs))
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    lines = ["# TO alone on the faithful tasks: every baseline from the naive guess", "",
             f"`python bench/to_alone.py --n {a.n} --n-slow {a.n_slow}` at commit `{rev}`, "
             f"{datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs "
             f"({a.jobs} runs at a time, 1 thread each). Instances: collection seed 0, indices 0..n-1. "
             "ms-fatrop: multiple shooting + fatrop (our optimizer, used for collection and gains); ss-ipopt: "
             "single shooting (controls only, states by rollout) + IPOPT "
             "with a limited-memory Hessian. Cap 1000 iterations, tolerance 1e-6. reached: converged, within the "
             "task's goal tolerance at T (pendulums 0.1 m, UR5 and quadrotor 0.05 m), constraints satisfied. Costs "
             "over converged solves.", "",
             "ddp: box-FDDP, the paper's solver family (sdp_cli/trajopt/ddp.py), all n instances as one batch; "
             "its times are iterations x the batch's wall time per instance-iteration.", "",
             "| task | baseline | n | converged | reached | mean cost | median cost | iterations | time mean / median (s) "
             "| the paper (TO alone) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for t, b in [(t, b) for t in a.tasks.split(",") for b in baselines if (t, b) in SKIP]:
        rows.append({"task": t, "baseline": b, "skipped": True})
    rows.sort(key=lambda r: (a.tasks.split(",").index(r["task"]), BASELINES.index(r["baseline"])))
    table = {}
    for r in rows:
        if r.get("skipped"):
            why = "single shooting with column constraints: > 2 min per solve in a probe"
            table[r["task"], r["baseline"]] = (f"| {r['task']} | {r['baseline']} | not run | | | | | | ({why}) | "
                                               f"{PAPER.get(r['task'], '')} |")
            continue
        if r["baseline"] == "ddp":
            table[r["task"], "ddp"] = (
                f"| {r['task']} | ddp (batch of {r['n']}) | {r['n']} | {r['converged']:.0%} | {r['reached']:.0%} "
                f"| {r['cost_mean']:.4g} | {r['cost_median']:.4g} | {r['iterations']:.1f} | "
                f"{r['time_mean']:.3f} / {r['time_median']:.3f} (batch wall / n: {r['batch_wall'] / r['n']:.3f}) "
                f"| {PAPER.get(r['task'], '')} |")
            continue
        table[r["task"], r["baseline"]] = (
            f"| {r['task']} | {r['baseline']} | {r['n']} | {r['converged']:.0%} | {r['reached']:.0%} | "
            f"{r['cost_mean']:.4g} | {r['cost_median']:.4g} | {r['iterations']:.1f} | "
            f"{r['time_mean']:.3f} / {r['time_median']:.3f} | {PAPER.get(r['task'], '')} |")
    if a.update and a.out and a.out.is_file():
        lines = _updated(a.out.read_text(), table, " ".join(sys.argv[1:]), rev)
    else:
        lines += list(table.values())
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)


def _updated(old: str, table: dict, args: str, rev: str) -> list[str]:
    """The earlier table ``old`` with the rows of ``table`` ``{(task, baseline): row}`` put in place of its rows of
    those pairs (new pairs after their task's last row), and a line under the header saying what was re-run."""
    lines, done = old.rstrip("\n").split("\n"), set()
    key = lambda ln: (ln.split("|")[1].strip(), ln.split("|")[2].strip().split(" ")[0])   # noqa: E731
    rows = [i for i, ln in enumerate(lines) if ln.startswith("| ") and not ln.startswith("| task |")]
    for i in rows:
        if key(lines[i]) in table:
            lines[i] = table[key(lines[i])]
            done.add(key(lines[i]))
    for k, row in table.items():
        if k not in done:
            at = max((i for i in rows if key(lines[i])[0] == k[0]), default=len(lines) - 1)
            lines.insert(at + 1, row)
            rows = [j + (j > at) for j in rows] + [at + 1]
    pairs = ", ".join(f"{t} {b}" for t, b in table)
    note = (f"Rows re-run by `python bench/to_alone.py {args}` at commit `{rev}`, {datetime.date.today()}: "
            f"{pairs}.")
    head = next(i for i, ln in enumerate(lines) if ln.startswith("| task |"))
    return lines[:head] + [note, ""] + lines[head:]


if __name__ == "__main__":
    main()

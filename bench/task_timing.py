"""Is every task well-posed for a policy that does not see time? Writes results/tasks/timing.md.

For each registered task, TO optima from the naive guess on ``--n`` instances (``sdp collect``'s
instances of seed 0), measured by :func:`sdp_cli.checks.timing.optimum_timing`: when the optimum enters
the goal tolerance for good (``t_in``) and is at rest (``t_rest``, ``||v|| <= 0.05``), its speed and
distance at ``T``, and the cost of playing its own actions k steps late / early relative to its cost.
Rule (decided before the runs, issue "A perfect learner..."): well-posed when one step late costs
<= 2x the optimum on every instance; UR5 also at rest and in tolerance from ``t <= T - 63``.

    python bench/task_timing.py [--n 5] [--tasks pendulum,ur5-fixed] [--out results/tasks/timing.md]
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.data.artifacts import code_revision
from sdp_cli.tasks import get_task, task_names
from sdp_cli.checks.contract import solve_instances
from sdp_cli.checks.timing import REST_SPEED, SHIFTS, WELL_POSED_LATE_RATIO, optimum_timing

UR5_REST_BY = 63   # the largest T_a UR5's pipelines use: at rest from T - 63


def rng(values) -> str:
    v = [x for x in values if x is not None and np.isfinite(x)]
    none = len(v) < len(values)
    if not v:
        return "never"
    lo, hi = min(v), max(v)
    s = f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g}"
    return s + (" (never on some)" if none else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5)
    ap.add_argument("--tasks", default=",".join(task_names()))
    ap.add_argument("--out", type=Path, default=Path("results/tasks/timing.md"))
    ap.add_argument("--conversion", default=None,
                    help="how the shifted state actions become controls (sdp_cli.tasks.conversion; default: each "
                         "task's own, as check-task and the rollouts)")
    args = ap.parse_args()
    rows, t0 = [], time.time()
    for name in args.tasks.split(","):
        task = get_task(name)
        arrays = solve_instances(task, args.n, max_attempts=10 * args.n)
        recs = [optimum_timing(task, X, U, xi, conversion=args.conversion)
                for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"])]
        df = pd.DataFrame(recs)
        late1 = df["late1"].max()
        ok = late1 <= WELL_POSED_LATE_RATIO
        note = ""
        if name.startswith("ur5"):
            by = task.T - UR5_REST_BY
            settled = all(r["t_rest"] is not None and r["t_rest"] <= by and r["t_in"] is not None and r["t_in"] <= by
                          for r in recs)
            ok = ok and settled
            note = f"; at rest and in tolerance by T - 63 = {by}: {'yes' if settled else 'NO'}"
        conv = None if task.action == "u" else (args.conversion or task.default_conversion)
        row = {"task": name, "conversion": conv or "(torques)", "T": task.T, "n": len(recs), "TO cost": rng(df.cost.round(3)),
               "t_in": rng(df.t_in), "t_rest": rng(df.t_rest), "speed at T": rng(df.speed_T.round(3)),
               "dist at T (m or rad)": rng(df.dist_T.round(4))}
        for k in SHIFTS:
            row[f"late {k}"] = rng(df[f"late{k}"].round(2))
        for k in SHIFTS:
            row[f"early {k}"] = rng(df[f"early{k}"].round(2))
        row["well-posed"] = ("yes" if ok else "NO") + f" (late 1 max {late1:.2f}x{note})"
        rows.append(row)
        print(name, row["well-posed"], flush=True)
    table = pd.DataFrame(rows)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = [
        "# Timing of the TO optimum per task (is the task well-posed for a policy without time?)", "",
        f"Written by `python bench/task_timing.py --n {args.n}"
        f"{f' --conversion {args.conversion}' if args.conversion else ''}` on {stamp}, code revision `{code_revision()}`, "
        f"{platform.node()} ({platform.machine()}, Python {platform.python_version()}), {time.time() - t0:.0f} s.", "",
        f"TO (fatrop, from the naive guess) on the first {args.n} converged instances of seed 0 per task. "
        "`t_in`: first step from which the goal distance stays within the task's tolerance; `t_rest`: first step "
        f"from which ||v|| <= {REST_SPEED} (rad/s; the quadrotor's body twist); speed and distance at T. "
        "`late k` / `early k`: cost of playing the optimum's own actions k steps late (a'_t = a_(t-k), holding x_0 "
        "at rest before) or early (a'_t = a_min(t+k, T-1)), divided by the optimum's cost; state actions are "
        "played as one chunk through the task's conversion (column `conversion`; `task.chunk_controller`) from "
        "the states reached, torques directly. Ranges are "
        "min-max over the instances.", "",
        f"Rule (decided before the runs): a task is well-posed when one step late costs <= {WELL_POSED_LATE_RATIO:g}x "
        "the optimum on every instance; UR5 also in tolerance and at rest from t <= T - 63 (Fig. 3's largest T_a). "
        "The pendulums keep the paper's explicit cost: their optimum swings into the goal near T and is still "
        "moving at T (the paper's task); one step late costs them little.", "",
        table.to_markdown(index=False), "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(text))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

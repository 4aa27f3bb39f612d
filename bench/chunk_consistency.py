"""How consistent a full-state policy's predicted chunks are with themselves: configuration against velocity.

A policy that predicts whole states (the quadrotor's action ``(dq, v)``, ``Task.action == "x"``) predicts each
row's configuration and its velocity separately. The task's dynamics ties them (semi-implicit Euler:
``q_{s+1} = q_s (+) dt v_{s+1}``), so along a trajectory of the task ``(q_{s+1} (-) q_s) / dt - v_{s+1}`` is zero
up to the integrator, and the stored TO optima show how near zero. The ``tracking`` conversion
(sdp_cli/tasks/conversion.py) follows the predicted configurations (0.05 m of tolerated position error on the
quadrotor) as well as the velocities, ``inverse-dynamics`` only the velocities; so a policy whose rows jump in
position far more than its velocities say is followed to those jumps under tracking and not under inverse
dynamics. This bench rolls out each run's final policy (the last iteration whose training finished) on its
first ``--n`` training instances under the task's default conversion, keeps every chunk it predicted (the rows
played), and prints per run the median and 90th percentile of ``|(q_{s+1} (-) q_s) / dt - v_{s+1}|`` over the
rows of the chunks (consecutive predicted rows; row 0 of a chunk, the state reached, is not compared), in tangent
units (m/s and rad/s for the quadrotor's base), the median over the first chunks alone (predicted from the
training instances' own starts, where the policy was trained), and the same over the stored optima of those
instances.

    python bench/chunk_consistency.py --runs runs/fig4 --prefix quadrotor- --methods sdp,dp --out results/fig4/chunk_consistency.md
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd


def row_mismatch(task, R: np.ndarray) -> np.ndarray:
    """``|(q_{s+1} (-) q_s) / dt - v_{s+1}|`` for consecutive rows of ``R (..., S, nx)``: ``(..., S - 1)``."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, *R.shape[-2:])
    out = np.empty((len(flat), flat.shape[1] - 1))
    for i, rows in enumerate(flat):
        for s in range(len(rows) - 1):
            dq = task.difference(rows[s], rows[s + 1])[: task.nv] / task.dt
            out[i, s] = np.linalg.norm(dq - rows[s + 1][task.nq:])
    return out.reshape(R.shape[:-2] + (R.shape[-2] - 1,))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="one or more runs folders")
    ap.add_argument("--prefix", default="quadrotor-", help="run folders whose name starts with this")
    ap.add_argument("--methods", default="sdp,dp")
    ap.add_argument("--n", type=int, default=10, help="training instances rolled out per run")
    ap.add_argument("--out", type=Path, default=None, help="also write the table here (markdown)")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from sdp_cli.algorithm.rollout import RolloutConfig, instance_generators, rollout_policy
    from sdp_cli.data.artifacts import code_revision

    from conversion_confirmation import final_policy, selected_runs   # bench/ is the script's sys.path[0]

    runs = [r for folder in a.runs for r in selected_runs(folder, a.prefix, a.methods.split(","))]
    if not runs:
        raise SystemExit(f"no finished run (with summary.csv) in {' '.join(map(str, a.runs))} named {a.prefix}* with a method in {a.methods}")
    rows, t0 = [], time.perf_counter()
    for run in runs:
        pol, data, t_a = final_policy(run)
        task = pol.task
        if task.action != "x":
            print(f"{run.name}: skipped (its actions are {task.action!r}, not whole states)")
            continue
        xis = data["xi"][: a.n]
        chunks = []
        build = task.chunk_controller

        def keep(x0, acts, conversion, build=build, chunks=chunks, task=task):
            chunks.append(task.states_from_actions(x0, acts)[:, 1:])   # the predicted rows, (n, S, nx)
            return build(x0, acts, conversion)

        task.chunk_controller = keep
        cfg = RolloutConfig(n=len(xis), seed=0, t_a=t_a).validate(pol)
        try:
            with torch.no_grad():
                rollout_policy(pol, xis, cfg, generators=instance_generators(0, range(len(xis))))
        finally:
            task.chunk_controller = build
        per_chunk = [row_mismatch(task, c).ravel() for c in chunks]
        first = per_chunk[0][np.isfinite(per_chunk[0])]                  # from the training starts themselves
        pred = np.concatenate(per_chunk)
        pred = pred[np.isfinite(pred)]
        opt = row_mismatch(task, data["X"][: a.n]).ravel()
        rows.append({"run": run.name, "task": pol.task_name, "method": pol.method, "T_a": cfg.t_a,
                     "conversion": task.default_conversion, "instances": len(xis),
                     "first chunk, median": float(np.median(first)),
                     "policy rows, median": float(np.median(pred)), "policy rows, p90": float(np.percentile(pred, 90)),
                     "TO optima, median": float(np.median(opt)), "TO optima, p90": float(np.percentile(opt, 90))})
        print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = "\n".join([
        "# Predicted chunks: configuration against velocity (bench/chunk_consistency.py)", "",
        f"Written by `python bench/chunk_consistency.py --runs {' '.join(map(str, a.runs))} --prefix {a.prefix} --methods {a.methods} "
        f"--n {a.n}` on {stamp}, code revision `{code_revision()}`, {platform.node()} ({platform.machine()}), "
        f"{time.perf_counter() - t0:.0f} s.", "",
        "Per run: its final policy rolled out on its first training instances under the task's default conversion; "
        "over the rows of every chunk it predicted, `|(q_{s+1} (-) q_s) / dt - v_{s+1}|` (tangent units: m/s and "
        "rad/s for the quadrotor's base), the median over the first chunks alone (predicted from the training "
        "starts themselves), beside the same over the stored TO optima of those instances (zero up to the "
        "integrator). See the script's docstring.", "",
        df.to_markdown(index=False, floatfmt=".3g") if len(df) else "(no run with whole-state actions)", ""])
    print(text)
    if a.out:
        a.out.write_text(text)


if __name__ == "__main__":
    main()

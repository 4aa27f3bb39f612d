"""alpha_Sobolev sweep and the tau_k-path ablation (issue "Learning side as the paper means it").

    python bench/alpha_sweep.py --task double_pendulum --n-traj 30 --epochs 3000 --horizon 16 --t-a 4 \\
        --alphas 0.001,0.01,0.1,1 --seeds 0,1,2 --out /work/sweeps/alpha-dp [--paths cond,total] [--jobs 2]

One iteration of Algorithm 1 (``sdp loop --n-algo 1``: collect ``--n-traj`` trajectories with seed
``1000 * seed``, train SDP for ``--epochs`` epochs, roll out on the ``--n-test`` test instances of
test seed 0; refined too unless ``--no-refine``) per (alpha, path, seed), each an independent process with one torch thread; runs that
finished are read back, so an interrupted sweep resumes where it stopped. Prints one row per run and
a table per (alpha, path): mean over seeds of the policy's mean cost, median cost and success rate
(the task's goal test at T, not diverged), and the seeds' spread.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd


def run_one(a, alpha: float, path: str, seed: int) -> dict:
    run = a.out / f"a{alpha:g}-{path}-s{seed}"
    summary = run / "summary.csv"
    if not summary.is_file():
        cmd = [sys.executable, "-m", "sdp_cli.cli", "loop", "--task", a.task, "--method", "sdp", "--n-algo", "1",
               "--n-traj", str(a.n_traj), "--epochs", str(a.epochs), "--horizon", str(a.horizon),
               "--t-a", str(a.t_a), "--n-test", str(a.n_test), "--seed", str(seed), "--sobolev-alpha", str(alpha),
               "--sobolev-path", path, "--workers", "1", "--threads", "1", "--out", str(run)]
        if a.no_refine:
            cmd.append("--no-eval-refine")
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"alpha {alpha} {path} seed {seed}: {r.stderr[-2000:]}")
    df = pd.read_csv(summary)
    last = df[df.iteration == df.iteration.max()].iloc[0]
    return {"alpha": alpha, "path": path, "seed": seed, "policy_cost_mean": float(last.policy_cost_mean),
            "policy_cost_median": float(last.policy_cost_median), "success_rate": float(last.success_rate),
            "refined_cost_mean": float(last.get("refined_cost_mean", float("nan"))),
            "to_alone_cost_mean": float(last.get("to_alone_cost_mean", float("nan")))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--n-traj", type=int, required=True)
    ap.add_argument("--epochs", type=int, required=True)
    ap.add_argument("--horizon", type=int, required=True)
    ap.add_argument("--t-a", type=int, required=True)
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--alphas", default="0.001,0.01,0.1,1")
    ap.add_argument("--paths", default="cond")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--no-refine", action="store_true",
                    help="skip the evaluation's refine (the sweep reports the policy's own metrics)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    jobs = [(float(al), p, int(s)) for s in a.seeds.split(",") for p in a.paths.split(",")
            for al in a.alphas.split(",")]
    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(lambda j: run_one(a, *j), jobs))
    df = pd.DataFrame(rows).sort_values(["path", "alpha", "seed"])
    print(df.to_string(index=False))
    agg = df.groupby(["path", "alpha"]).agg(
        seeds=("seed", "count"), cost_mean=("policy_cost_mean", "mean"), cost_min=("policy_cost_mean", "min"),
        cost_max=("policy_cost_mean", "max"), cost_median=("policy_cost_median", "mean"),
        success=("success_rate", "mean"), refined=("refined_cost_mean", "mean"))
    print(agg.to_string(float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main()

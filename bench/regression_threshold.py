"""Re-derive the threshold of tests/test_regression_small.py (the `small` experiment).

    python bench/regression_threshold.py [--seeds 0,1,2,3,4] [--threads 1,2] [--thread-seeds 0,1]
                                         [--variants sdp,alpha0,flipped,dp] [--jobs 2] [--out /tmp/regr]

Runs the `small` experiment's Algorithm 1 (pendulum, 2 iterations x 10 trajectories x 700 epochs,
T_h 16, T_a 8, batch 128, 20 test instances; pipelines/small.yaml) with `sdp loop`, once per
seed and torch thread count, for

- ``sdp``: the method as shipped;
- ``alpha0``: SDP with alpha_Sobolev = 0 (the Sobolev term switched off);
- ``flipped``: SDP trained on negated target Jacobians (a sign bug in the gains or the chain rule);
- ``dp``: diffusion policy, for reference,

and prints, per variant, the SDP policy's success rate (rollouts whose end effector ends within the
task's goal tolerance, not diverged), median and mean cost at the last iteration, then, for each
broken variant, a threshold on the mean cost (the regression test's first check) halfway between
the worst working run and the best broken one, if the two are separated, and a threshold on SDP's
final training Sobolev error (its second check, which catches alpha_Sobolev = 0). Whoever changes a task or the training re-runs this script and
updates the test's constants and docstring with its output. Runs are independent processes with
one torch thread each unless --threads says otherwise; ``--jobs`` run at the same time.
``dvc repro`` runs the same ``sdp loop`` (the DVC stage ``group``), so the test's run is this script's
seed 0 on 1 thread.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

SMALL = ["--task", "pendulum", "--n-algo", "2", "--n-traj", "10", "--epochs", "700", "--horizon", "16",
         "--t-a", "8", "--eval-t-a", "8", "--n-test", "20", "--batch-size", "128", "--workers", "1"]
VARIANTS = {"sdp": ["--method", "sdp"], "alpha0": ["--method", "sdp", "--sobolev-alpha", "0"],
            "flipped": ["--method", "sdp"], "dp": ["--method", "dp"]}


def run_one(variant: str, seed: int, threads: int, out: Path) -> dict:
    """One loop in a subprocess (``--one`` mode below); the last iteration's summary row."""
    run = out / f"{variant}-s{seed}-t{threads}"
    summary = run / "summary.csv"
    if not summary.is_file():
        cmd = [sys.executable, __file__, "--one", variant, "--", "loop", *SMALL, *VARIANTS[variant], "--seed", str(seed),
               "--threads", str(threads), "--out", str(run)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{variant} seed {seed}: {r.stderr[-2000:]}")
    df = pd.read_csv(summary)
    last = df[df.iteration == df.iteration.max()].iloc[0]
    sob = pd.read_csv(run / f"it{int(last.iteration)}" / "policy" / "metrics.csv").sobolev.tail(50).mean()
    return {"variant": variant, "seed": seed, "threads": threads, "success_rate": float(last.success_rate),
            "sobolev_final": float(sob),
            "policy_cost_median": float(last.policy_cost_median), "policy_cost_mean": float(last.policy_cost_mean)}


def one(variant: str, argv: list[str]) -> None:
    """Run ``sdp loop argv`` in this process; ``flipped`` negates the Sobolev targets first."""
    if variant == "flipped":
        import sdp_cli.policy.diffusion as diffusion

        orig = diffusion.DiffusionUnetPolicy.loss_from   # the jvp-mode loss of every run, solo or stacked
        diffusion.DiffusionUnetPolicy.loss_from = lambda self, d, y, ydots: orig(
            self, {**d, "J": -d["J"]} if "J" in d else d, y, ydots)
    from sdp_cli.cli import app

    app(argv, standalone_mode=True)


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--one":
        return one(sys.argv[2], sys.argv[4:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--thread-seeds", default=None, help="seeds also run at the other thread counts (default all)")
    ap.add_argument("--variants", default="sdp,alpha0,flipped,dp")
    ap.add_argument("--other-seeds", default=None, help="seeds of the variants other than sdp (default: --seeds)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("/tmp/sdp-regression-threshold"))
    a = ap.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    threads = [int(t) for t in a.threads.split(",")]
    tseeds = seeds if a.thread_seeds is None else [int(s) for s in a.thread_seeds.split(",")]
    oseeds = seeds if a.other_seeds is None else [int(s) for s in a.other_seeds.split(",")]
    jobs = [(v, s, t) for s in seeds for v in a.variants.split(",") if v == "sdp" or s in oseeds
            for t in (threads if v == "sdp" and s in tseeds else threads[:1])]
    a.out.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(lambda j: run_one(*j, a.out), jobs))
    df = pd.DataFrame(rows).sort_values(["variant", "threads", "seed"])
    print(df.to_string(index=False))
    agg = df.groupby(["variant", "threads"]).agg(success_min=("success_rate", "min"),
                                                 success_median=("success_rate", "median"),
                                                 success_max=("success_rate", "max"),
                                                 cost_median=("policy_cost_median", "median"))
    print(agg.to_string())
    ok = df[df.variant == "sdp"].policy_cost_mean
    for v in ("alpha0", "flipped"):
        broken = df[df.variant == v].policy_cost_mean
        if len(ok) and len(broken):
            hi, lo = float(ok.max()), float(broken.min())
            verdict = f"threshold {(hi + lo) / 2:.1f}" if lo > hi else "NOT separated: the test cannot catch it"
            print(f"policy mean cost, worst working SDP run {hi:.2f}; best {v} run {lo:.2f}: {verdict}")
    ok = df[df.variant == "sdp"].sobolev_final
    broken = df[df.variant == "alpha0"].sobolev_final
    if len(ok) and len(broken):
        hi, lo = float(ok.max()), float(broken.min())
        verdict = f"threshold {np.sqrt(hi * lo):.3g} (geometric midpoint)" if lo > hi else "NOT separated"
        print(f"final Sobolev error (last 50 steps), worst working SDP run {hi:.3g}; best alpha0 run {lo:.3g}: "
              f"{verdict}")

if __name__ == "__main__":
    main()

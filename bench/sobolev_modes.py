"""Does the default Sobolev estimator (x-side projection, JVP) train as well as eq. (6)'s?

    python bench/sobolev_modes.py --data DATASET [--epochs 1500] [--horizon 16] [--t-a 4] [--seeds 0,1,2] [--jobs 2]

Trains SDP with ``--sobolev-mode jvp`` (default) and ``vjp`` (eq. (6): output-side
projection, double backward) for each seed, rolls every policy out on the same 50 test
instances (``sdp rollout``'s test set) and prints the mean cost per run, the mean over
seeds per mode and their ratio (required: within 10%). Each job uses one torch thread.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def run_one(data: str, out: str, mode: str, seed: int, epochs: int, horizon: int, n_test: int,
            t_a: int | None) -> dict:
    import torch

    torch.set_num_threads(1)
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.algorithm.rollout import RolloutConfig, rollout
    from sdp_cli.training.train import train

    t0 = time.perf_counter()
    run = Path(out) / f"{mode}-s{seed}"
    ck = train(data, run, TrainConfig.of(method="sdp", epochs=epochs, seed=seed, horizon=horizon, sobolev_mode=mode),
               device="cpu", progress=False, log=lambda *_: None, resume=(run / "checkpoint.pt").exists())
    t_train = time.perf_counter() - t0
    _, s = rollout(ck, run / f"rollout-ta{t_a}.npz", RolloutConfig(n=n_test, seed=0, t_a=t_a))
    return {"mode": mode, "seed": seed, "mean_cost": s["mean_cost"], "median_cost": s["median_cost"],
            "diverged": s["diverged"], "train_s": t_train}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--epochs", type=int, default=1500)
    ap.add_argument("--horizon", type=int, default=16)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--t-a", type=int, default=4, help="actions played per prediction in the test rollouts")
    ap.add_argument("--out", default=None, help="run folder (default: a temporary folder)")
    a = ap.parse_args()
    out = a.out or tempfile.mkdtemp(prefix="sdp-modes-")
    seeds = [int(s) for s in a.seeds.split(",")]
    jobs = [(a.data, out, m, s, a.epochs, a.horizon, a.n_test, a.t_a) for s in seeds for m in ("jvp", "vjp")]
    with ProcessPoolExecutor(a.jobs) as ex:
        res = list(ex.map(run_one, *zip(*jobs)))
    import numpy as np
    ds = np.load(a.data)
    print(f"data {a.data}: TO mean cost {float(ds['cost'].mean()):.2f}; epochs {a.epochs}, T_h {a.horizon}, "
          f"T_a {a.t_a}, {a.n_test} test instances; runs in {out} (finished runs there are reused)")
    for r in res:
        print(f"{r['mode']:4s} seed {r['seed']}: mean cost {r['mean_cost']:.2f}  median {r['median_cost']:.2f}  "
              f"diverged {r['diverged']}  train {r['train_s']:.0f} s")
    means = {m: statistics.mean(r["mean_cost"] for r in res if r["mode"] == m) for m in ("jvp", "vjp")}
    train_s = {m: statistics.mean(r["train_s"] for r in res if r["mode"] == m) for m in ("jvp", "vjp")}
    print(f"mean over seeds: jvp {means['jvp']:.2f}, vjp {means['vjp']:.2f}; ratio jvp/vjp "
          f"{means['jvp'] / means['vjp']:.3f}; train time jvp/vjp {train_s['jvp'] / train_s['vjp']:.2f}")


if __name__ == "__main__":
    os.environ.setdefault("SDP_NO_PROGRESS", "1")
    main()

"""Rollout speed: Algorithm 2 batched over test instances vs one instance at a time.

    python bench/rollout.py [--policy RUN] [--task double_pendulum] [--n 50] [--t-a 9] [--k-rollout 5]

Without --policy, a double-pendulum SDP policy is collected and trained on a small budget first
(the speed of a rollout does not depend on how well the policy is trained). Prints the total and
per-instance wall time of the batched rollout, of the same instances rolled out one by one, and
their ratio, all measured in this run. The paper reports 1.1 s for one rollout on a laptop GPU.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _train_default(task: str, root: Path) -> Path:
    from sdp_cli.algorithm.collect import CollectConfig, collect
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.training.train import train

    data, _ = collect(CollectConfig(task=task, n_traj=10, seed=0), root / "data.npz", workers=1)
    cfg = TrainConfig.of(**{"method": "sdp", "epochs": 20, "horizon": 16})
    train(data, root / "sdp", cfg, device="cpu", progress=False, log=lambda s: None)
    return root / "sdp"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path)
    ap.add_argument("--task", default="double_pendulum")
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--t-a", type=int, default=9)
    ap.add_argument("--k-rollout", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as `sdp rollout`)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    from sdp_cli.policy import load_policy
    from sdp_cli.algorithm.rollout import RolloutConfig, evaluation_xis, instance_generators, rollout_policy

    with tempfile.TemporaryDirectory() as tmp:
        path = args.policy or _train_default(args.task, Path(tmp))
        pol = load_policy(path)
    cfg = RolloutConfig(n=args.n, seed=0, t_a=args.t_a, k_rollout=args.k_rollout).validate(pol)
    xis = evaluation_xis(pol.task, args.n, 0)
    with torch.no_grad():
        rollout_policy(pol, xis[:2], cfg)  # warm-up (scheduler, casadi map)
        t0 = time.perf_counter()
        batch = rollout_policy(pol, xis, cfg, generators=instance_generators(0, range(args.n)))
        t_batch = time.perf_counter() - t0
        t0 = time.perf_counter()
        ones = [rollout_policy(pol, xis[i:i + 1], cfg, generators=instance_generators(0, [i]))
                for i in range(args.n)]
        t_one = time.perf_counter() - t0
    # batched and one-by-one differ only by float32 summation order; a chaotic or diverging
    # rollout amplifies that, so compare the first chunk and count the trajectories that agree
    first = max(float(np.max(np.abs(o["U"][0, :cfg.t_a] - batch["U"][i, :cfg.t_a]))) for i, o in enumerate(ones))
    agree = sum(bool(np.allclose(o["X"][0], batch["X"][i], atol=1e-3, equal_nan=True)) for i, o in enumerate(ones))
    print(f"task {pol.task_name}, method {pol.method}, n = {args.n}, T = {pol.task.T}, T_h = {pol.T_h}, "
          f"T_a = {cfg.t_a}, K = {cfg.k_rollout}, torch threads = {torch.get_num_threads()}")
    print(f"batched    : {t_batch:8.3f} s total, {t_batch / args.n * 1e3:8.2f} ms per instance")
    print(f"one by one : {t_one:8.3f} s total, {t_one / args.n * 1e3:8.2f} ms per instance")
    print(f"ratio one-by-one / batched = {t_one / t_batch:.1f}x; first chunk max |U_batched - U_one| = {first:.1e}; "
          f"{agree}/{args.n} whole trajectories agree to 1e-3")
    print(f"paper: 1.1 s for one rollout on a laptop GPU -> batched total / 1.1 s = {t_batch / 1.1:.2f}")


if __name__ == "__main__":
    main()

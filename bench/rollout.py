"""Rollout speed: Algorithm 2 batched over test instances vs one instance at a time.

    python bench/rollout.py [--policy RUN] [--task double_pendulum] [--n 50] [--t-a 9] [--k-rollout 5] [--traced]

Without --policy, a double-pendulum SDP policy is collected and trained on a small budget first
(the speed of a rollout does not depend on how well the policy is trained). Prints the total and
per-instance wall time of the batched rollout, of the same instances rolled out one by one, and
their ratio, all measured in this run. The paper reports 1.1 s for one rollout on a laptop GPU.

``--traced``: the batched rollout also with the U-Net frozen into TorchScript (``torch.jit.trace``, ``freeze``,
``optimize_for_inference``), timed round-robin with the eager one in process CPU time, with the largest
difference of their controls (a frozen graph rounds otherwise; the package does not use it).
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
    ap.add_argument("--traced", action="store_true", help="also time a frozen TorchScript U-Net (see above)")
    ap.add_argument("--rounds", type=int, default=5, help="--traced: eager/traced rounds")
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
    if args.traced:
        _traced(pol, xis, cfg, args)


def _traced(pol, xis, cfg, args) -> None:
    """The batched rollout with the eager U-Net and with a frozen traced one, round-robin, process CPU time."""
    import statistics

    from sdp_cli.algorithm.rollout import instance_generators, rollout_policy

    eager = pol.unet
    with torch.no_grad():
        tau = torch.zeros(args.n, pol.T_h, pol.dims["n_action"])
        cond = torch.zeros(args.n, pol.dims["n_xi"] + pol.T_o * pol.dims["n_obs"])
        k = torch.zeros(args.n, dtype=torch.long)
        traced = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(eager.eval(), (tau, k, cond))))
    times = {"eager": [], "traced": []}
    outs = {}
    with torch.no_grad():
        for _ in range(args.rounds):
            for name, net in (("eager", eager), ("traced", traced)):
                pol.unet = net
                t0 = time.process_time()
                outs[name] = rollout_policy(pol, xis, cfg, generators=instance_generators(0, range(args.n)))
                times[name].append(time.process_time() - t0)
    pol.unet = eager
    e, t = statistics.median(times["eager"]), statistics.median(times["traced"])
    du = float(np.max(np.abs(outs["eager"]["U"][:, :cfg.t_a] - outs["traced"]["U"][:, :cfg.t_a])))
    print(f"batched, process CPU time (median of {args.rounds}): eager {e:.3f} s, traced+frozen {t:.3f} s, "
          f"{e / t:.2f}x; first chunk max |U_eager - U_traced| = {du:.1e}")


if __name__ == "__main__":
    main()

"""Where one solo training step's time goes (issue "Many runs at once": profile first).

    python bench/profile_step.py [dp|sdp] [B] [R]

Times, with one torch thread, the parts of the trainer's step on a synthetic batch of UR5's shapes (A 12,
n_obs 24, n_xi 6, ndx 12, T_h 32, the default U-Net): batch gathering, loss (the policy's ``compute_loss``),
backward, gradient clipping, AdamW (fused), the LR schedule, EMA (diffusers' ``EMAModel``, foreach) and reading the
metrics row; medians of 50 steps after 10 warm-up steps, printed in ms.

With ``R``: instead, one step of a stack of R such runs (``sdp_cli.training.train_step.Stack``, as ``sdp pipeline --run``
trains them, on ``ur5-fixed``'s shapes), 10 steps under torch's profiler after 3 warm-up steps; prints the share
of the CPU time of the ops that take most of it.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch
from diffusers.optimization import get_scheduler
from diffusers.training_utils import EMAModel

from sdp_cli.experiments.estimate import _synthetic_batch
from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.registry import make_policy


def stacked(method: str, B: int, R: int) -> None:
    from torch.profiler import ProfilerActivity, profile

    import sdp_cli.experiments.estimate as est

    steps = []
    real, est._median_seconds = est._median_seconds, lambda step, *_: steps.append(step) or 1.0
    try:
        est.stacked_step_seconds([("ur5-fixed", method, 32, None, None)] * R, B)   # builds the stack, hands back its step
    finally:
        est._median_seconds = real
    for _ in range(3):
        steps[0]()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(10):
            steps[0]()
    ev = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in ev)
    print(f"stack of {R} {method} runs, B {B} ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, 1 thread):"
          f" {total / 10 / 1e3:.1f} ms of CPU a step; " +
          ", ".join(f"{e.key} {100 * e.self_cpu_time_total / total:.0f}%" for e in ev[:12]))


def main() -> None:
    torch.set_num_threads(1)
    method = sys.argv[1] if len(sys.argv) > 1 else "sdp"
    B = int(sys.argv[2]) if len(sys.argv) > 2 else 32
    if len(sys.argv) > 3:
        return stacked(method, B, int(sys.argv[3]))
    T_h = 32
    dims = {"n_action": 12, "n_obs": 24, "n_xi": 6, "ndx": 12}
    cfg = TrainConfig.of(method=method, horizon=T_h, batch_size=B)
    torch.manual_seed(0)
    pol = make_policy(cfg, dims)
    opt = torch.optim.AdamW(pol.parameters(), lr=1e-3, betas=(0.95, 0.999), weight_decay=1e-6, fused=True)
    sched = get_scheduler("cosine", opt, num_warmup_steps=10, num_training_steps=100000)
    ema = EMAModel(pol.parameters(), decay=0.9999, use_ema_warmup=True, inv_gamma=1.0, power=0.75, foreach=True)
    gen = torch.Generator().manual_seed(0)
    batch = _synthetic_batch(method, dims, T_h, 4 * B, gen, "cpu")
    params = list(pol.parameters())
    T = {k: [] for k in ("gather", "loss", "backward", "clip", "opt", "sched", "ema", "metrics")}
    for it in range(60):
        t = [time.perf_counter()]
        idx = torch.randperm(4 * B, generator=gen)[:B]
        b = {k: v[idx] for k, v in batch.items()}
        t.append(time.perf_counter())
        loss, parts = pol.compute_loss(b, gen)
        t.append(time.perf_counter())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t.append(time.perf_counter())
        g = torch.nn.utils.clip_grad_norm_(params, 1.0)
        t.append(time.perf_counter())
        opt.step()
        t.append(time.perf_counter())
        sched.step()
        t.append(time.perf_counter())
        ema.step(params)
        t.append(time.perf_counter())
        (f"{loss.item():.6g}", f"{parts['dp'].item():.6g}", f"{parts['sobolev'].item():.6g}", f"{float(g):.4g}")
        t.append(time.perf_counter())
        if it >= 10:
            for k, a, z in zip(T, t[:-1], t[1:]):
                T[k].append(z - a)
    tot = sum(np.median(v) for v in T.values())
    print(f"{method} B {B} ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, 1 thread): total "
          f"{1e3 * tot:.1f} ms; " + ", ".join(f"{k} {1e3 * np.median(v):.2f}" for k, v in T.items()))


if __name__ == "__main__":
    main()

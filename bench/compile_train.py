"""Eager against compiled training steps (``TrainConfig.compile``), measured side by side in one process, with the
compile's cost cold and warm and the break-even in steps.

    python bench/compile_train.py [--configs ur5-sdp-32,ur5-dp-32,dp2-sdp-158,ur5-sdp-32-r8,ur5-dp-32-r8]
                                  [--rounds 20]

A config is ``<task>-<method>-<B>[-r<R>]``: ``ur5`` (fig1's UR5, T_h 32), ``dp2`` (fig2's double pendulum,
T_h 16), R runs as one stack (``sdp pipeline --run``). Per config, one subprocess with an empty inductor cache
builds the trainer's own step (``sdp_cli.experiments.estimate.step_seconds`` / ``stacked_step_seconds``: draws, loss, backward,
clipping, AdamW, EMA) eager and compiled, times the compiled one's first step (the cold compile, process CPU time,
inductor's worker threads included), then times both round-robin in CPU time of the calling thread (one torch
thread), and prints the medians; a second subprocess on the now warm cache times the compile again (warm). The
break-even is the compile's CPU time over the CPU time a compiled step saves; a run of fewer steps trains faster
eager. Run steps per second count R runs of a stack.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

SHAPES = {"ur5": ("ur5-fixed", 32), "dp2": ("double_pendulum", 16)}


def _step(task, method, T_h, B, R, compile_on):
    """The trainer's step of this config (its first call not yet made)."""
    import sdp_cli.experiments.estimate as est
    from sdp_cli.policy.config import TrainConfig

    steps = []
    real = est._median_seconds
    est._median_seconds = lambda step, *a, **k: steps.append(step) or 0.0
    try:
        cfg = TrainConfig.of(method=method, horizon=T_h, batch_size=B, compile=compile_on)
        if R == 1:
            est.step_seconds(task, method, T_h, B, train=cfg)
        else:
            est.stacked_step_seconds([(task, method, T_h, None, cfg)] * R, B)
    finally:
        est._median_seconds = real
    return steps[0]


def one(config: str, rounds: int, warm_only: bool) -> dict:
    import torch

    torch.set_num_threads(1)
    parts = config.split("-")
    (task, T_h), method, B = SHAPES[parts[0]], parts[1], int(parts[2])
    R = int(parts[3][1:]) if len(parts) > 3 else 1
    comp = _step(task, method, T_h, B, R, True)
    t0 = time.process_time()
    comp()
    out = {"config": config, "compile_cpu_s": time.process_time() - t0}
    if warm_only:
        return out
    eager = _step(task, method, T_h, B, R, False)
    eager()
    for _ in range(2):   # a smaller batch would recompile; the same batch runs the compiled graph
        comp()
    times = {"eager": [], "compiled": []}
    for _ in range(rounds):
        for name, f in (("eager", eager), ("compiled", comp)):
            t = time.thread_time()
            f()
            times[name].append(time.thread_time() - t)
    out.update({k: statistics.median(v) for k, v in times.items()}, R=R)
    return out


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        print(json.dumps(one(sys.argv[2], int(sys.argv[3]), sys.argv[4] == "warm")))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="ur5-sdp-32,ur5-dp-32,dp2-sdp-158,ur5-sdp-32-r8,ur5-dp-32-r8")
    ap.add_argument("--rounds", type=int, default=20)
    a = ap.parse_args()
    import torch

    print(f"{time.strftime('%Y-%m-%d %H:%M')} torch {torch.__version__}, 1 thread, {os.cpu_count()} cpus, "
          f"load {os.getloadavg()[0]:.1f}")
    print("| config | R | eager ms/step | compiled ms/step | speed-up | cold compile CPU-s | warm compile CPU-s "
          "| break-even steps (cold / warm) |")
    print("|---|---|---|---|---|---|---|---|")
    for config in a.configs.split(","):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
            run = lambda mode: json.loads(subprocess.run(   # noqa: E731
                [sys.executable, __file__, "--one", config, str(a.rounds), mode], env=env, check=True,
                capture_output=True, text=True).stdout.strip().splitlines()[-1])
            cold = run("cold")
            warm = run("warm")
        saved = cold["eager"] - cold["compiled"]
        be = lambda s: f"{s / saved:.0f}" if saved > 0 else "never"   # noqa: E731
        print(f"| {config} | {cold['R']} | {1e3 * cold['eager']:.1f} | {1e3 * cold['compiled']:.1f} | "
              f"{cold['eager'] / cold['compiled']:.2f}x | {cold['compile_cpu_s']:.0f} | {warm['compile_cpu_s']:.0f} | "
              f"{be(cold['compile_cpu_s'])} / {be(warm['compile_cpu_s'])} |", flush=True)


if __name__ == "__main__":
    main()

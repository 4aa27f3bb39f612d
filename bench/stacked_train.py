"""Run-steps per second of R U-Nets stacked in one module (sdp_cli.policy.unet, members=R) against R solo networks,
measured side by side in one run (issue "Many runs at once").

    python bench/stacked_train.py [--stacks 1,5,10,25] [--batches 16,64] [--shapes ur5,quadrotor,double_pendulum]
                                  [--rounds 5] [--threads 1] [--device cpu] [--trainer]

A *network step* of one run: the loss (DP: eq. (2)'s regression of the denoised chunk; SDP: the same plus the
jvp-mode Sobolev term, the network's hand-written tangent propagation along one random state direction),
backward, gradient clipping, AdamW and an EMA update, on synthetic normalized batches of the given shape
(A actions, n_cond condition, T_h 32 or 16, the paper's U-Net [24, 24, 32, 32]). Solo: R separate networks
stepped one after the other (what R runs in one process cost today); stacked: one ConditionalUnet1D of R members
and one optimizer over it. Both are timed round-robin; the median per configuration is printed with the ratio
(stacked run-steps/s over solo run-steps/s). The stacked step here clips and schedules all members alike; the
per-member clipping, schedules and random streams of a stacked trainer add a few small ops per step.

``--trainer``: instead, the trainer's own steps on a real task's shapes: one step of R runs of
``sdp_cli.training.train_step.Stack`` (per-member draws, the stacked network, each member's own clipping, AdamW and
EMA, as ``sdp pipeline --run`` trains them) against R steps of ``sdp_cli.training.train_step.step`` of one run (``OneRun``),
both measured by ``sdp_cli.experiments.estimate`` (``stacked_step_seconds``, ``step_seconds``) in this one run, and beside
them the solo step as it was when the issue was filed (38d2c04: AdamW's foreach path, diffusers' per-tensor EMA;
the issue's goal is >= 3x that).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from sdp_cli.policy.unet import ConditionalUnet1D, stack_members

#: (A, n_cond, T_h): fig1's UR5 (12 joint positions; xi 6 + o 24), quadrotor (4 rotor thrusts; xi 3 + o 17),
#: fig2's double pendulum (2 torques; xi 2 + o 6, T_h 16)
SHAPES = {"ur5": (12, 30, 32), "quadrotor": (4, 20, 32), "double_pendulum": (2, 8, 16)}
ARCH = dict(down_dims=(24, 24, 32, 32), kernel_size=5, n_groups=8, step_embed_dim=64)


def ema_step(shadow, params, decay=0.999):
    d = torch._foreach_sub(shadow, params)
    torch._foreach_mul_(d, 1 - decay)
    torch._foreach_sub_(shadow, d)


def make_step(net, opt, shadow, sobolev: bool, batch):
    params = list(net.parameters())

    def step():
        tau, k, cond, target, tau_d, cond_d, jt = batch
        if sobolev:
            y, yd = net.forward_jvp(tau, tau_d, k, cond, cond_d)
            loss = ((y - target) ** 2).mean() + ((yd - jt) ** 2).mean()
        else:
            loss = ((net(tau, k, cond) - target) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        with torch.no_grad():
            ema_step(shadow, params)
        loss.item()
    return step


def batches(R, B, A, nc, T, stacked: bool, device):
    g = torch.Generator().manual_seed(0)
    r = lambda *s: torch.randn(*s, generator=g).to(device)   # noqa: E731
    tau, target, jt = r(B, R, T, A), r(B, R, T, A), r(B, R, T, A)
    cond, cond_d, tau_d = r(B, R, nc), r(B, R, nc), r(B, R, T, A)
    k = torch.randint(0, 5, (B, R), generator=g).to(device)
    if stacked:
        return [(tau, k, cond, target, tau_d, cond_d, jt)]
    return [tuple(t[:, i] for t in (tau, k, cond, target, tau_d, cond_d, jt)) for i in range(R)]


def setup(R, B, shape, sobolev, stacked, device):
    A, nc, T = SHAPES[shape]
    torch.manual_seed(0)
    nets = [ConditionalUnet1D(A, nc, **ARCH) for _ in range(R)]
    if stacked:
        nets = [stack_members(nets)]
    nets = [n.to(device) for n in nets]
    steps = []
    for net, b in zip(nets, batches(R, B, A, nc, T, stacked, device)):
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4, foreach=True)
        shadow = [p.detach().clone() for p in net.parameters()]
        steps.append(make_step(net, opt, shadow, sobolev, b))
    return lambda: [s() for s in steps]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stacks", default="1,5,10,25")
    ap.add_argument("--batches", default="16,64")
    ap.add_argument("--shapes", default="ur5,quadrotor,double_pendulum")
    ap.add_argument("--modes", default="dp,sdp")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--trainer", action="store_true", help="the trainer's steps (sdp_cli.training.train_step.Stack)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    print(f"torch {torch.__version__}, {a.threads} thread(s), device {dev}; {time.strftime('%Y-%m-%d %H:%M')}")
    if a.trainer:
        return trainer_table(a, dev)
    print("| shape | mode | B | R | solo run-steps/s | stacked run-steps/s | stacked / solo |")
    print("|---|---|---|---|---|---|---|")
    for shape in a.shapes.split(","):
        for mode in a.modes.split(","):
            for B in (int(b) for b in a.batches.split(",")):
                for R in (int(r) for r in a.stacks.split(",")):
                    fns = {s: setup(R, B, shape, mode == "sdp", s, dev) for s in (False, True)}
                    for f in fns.values():      # warm-up
                        f()
                    sync()
                    times = {s: [] for s in fns}
                    for _ in range(a.rounds):
                        for s, f in fns.items():
                            t0 = time.perf_counter()
                            f()
                            sync()
                            times[s].append(time.perf_counter() - t0)
                    solo, st = (R / statistics.median(times[s]) for s in (False, True))
                    print(f"| {shape} | {mode} | {B} | {R} | {solo:.1f} | {st:.1f} | {st / solo:.2f}x |", flush=True)


#: the trainer table's tasks: fig1's UR5 and quadrotor, fig2's double pendulum (T_h 16)
TASKS = {"ur5": ("ur5-fixed", 32), "quadrotor": ("quadrotor-0", 32), "double_pendulum": ("double_pendulum", 16)}


def _solo_38d2c04():
    """The solo trainer's optimisation as it was when the issue was filed (38d2c04): AdamW's foreach path and
    diffusers' per-tensor EMA, in place of the trainer's fused AdamW and foreach EMA while it is in effect."""
    import contextlib

    from diffusers.training_utils import EMAModel

    import sdp_cli.training.train as tr

    @contextlib.contextmanager
    def ctx():
        saved = tr.optimizer_for, tr.ema_for
        tr.optimizer_for = lambda cfg, params: torch.optim.AdamW(
            params, lr=cfg.optim.lr, betas=tuple(cfg.optim.betas), weight_decay=cfg.optim.weight_decay, foreach=True)
        tr.ema_for = lambda cfg, params: EMAModel(params, decay=cfg.optim.ema_max_decay, use_ema_warmup=True,
                                                  inv_gamma=1.0, power=cfg.optim.ema_power)
        try:
            yield
        finally:
            tr.optimizer_for, tr.ema_for = saved
    return ctx()


def trainer_table(a, dev) -> None:
    from sdp_cli.experiments.estimate import stacked_step_seconds, step_seconds

    print("| task | method | B | R | solo at 38d2c04 run-steps/s | solo run-steps/s | stacked run-steps/s | "
          "stacked / solo | stacked / solo at 38d2c04 |")
    print("|---|---|---|---|---|---|---|---|---|")
    for shape in a.shapes.split(","):
        task, T_h = TASKS[shape]
        for method in a.modes.split(","):
            for B in (int(b) for b in a.batches.split(",")):
                with _solo_38d2c04():
                    old = 1 / step_seconds(task, method, T_h, B, device=str(dev), max_s=a.rounds)
                for R in (int(r) for r in a.stacks.split(",")):
                    solo = 1 / step_seconds(task, method, T_h, B, device=str(dev), max_s=a.rounds)
                    st = R / stacked_step_seconds([(task, method, T_h, None, None)] * R, B, device=str(dev), max_s=a.rounds)
                    print(f"| {task} | {method} | {B} | {R} | {old:.1f} | {solo:.1f} | {st:.1f} | {st / solo:.2f}x | "
                          f"{st / old:.2f}x |", flush=True)


if __name__ == "__main__":
    main()

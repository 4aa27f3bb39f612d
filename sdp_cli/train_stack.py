"""Many runs at once: train R compatible diffusion runs as one stacked U-Net (:mod:`sdp_cli.policy.stacked_unet`).

The paper's U-Net is tiny, so a step of one run is mostly per-op overhead; R runs stacked as one network cost
little more than one (``bench/stacked_train.py``). Everything else of a run stays its own and is the solo
trainer's (:class:`sdp_cli.train.Run`): dataset, epoch order, random stream (noise, diffusion steps, Sobolev
projections, drawn in a solo run's order), normalizer and Sobolev scale, AdamW state, LR schedule, EMA, gradient
clipping, ``save_at`` checkpoints, metrics and checkpoints. Each member's U-Net weights are *views* into the
stacked network, and its AdamW moments and EMA weights views into the rows of
:class:`sdp_cli.stack_optim.StackedOptimisation`'s matrices, which step every member's clipping, AdamW and EMA in
a few whole-stack operations with its own settings; a member's checkpoint is a solo checkpoint (``load_policy``, ``sdp train --resume``), and a killed stack resumes every member.

A run trained in a stack equals the same run trained alone to float32 rounding (the grouped kernels sum in another
order; ``tests/test_train_stack.py``), whichever runs share its stack. Compatible runs (:func:`stack_key`): the same
task, method, architecture (T_h, T_o, K, action, U-Net), batch size and Sobolev mode, path, projections and
fraction; seeds, datasets (n_traj), epochs, alpha, learning rates and the other optimisation settings may differ.
Members whose batches are smaller (a smaller dataset's last batch of an epoch, a finished run) are padded and
their padded rows left out of their losses; a finished member stays in the stack but takes no step.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Callable

import torch

from sdp_cli.errors import SdpError
from sdp_cli.losses.sobolev import random_unit
from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.diffusion import chunk_tangents
from sdp_cli.stack_optim import StackedOptimisation

#: the default number of runs per stack (fixed, not chosen by the machine: same seed, same bytes on every machine
#: with torch's CPU kernels capped: sdp_cli/kernels.py)
DEFAULT_STACK = 8


def stackable(cfg: TrainConfig) -> bool:
    """Runs of this config can share a stack: the method's family opts in (``Policy.stackable``: the diffusion
    U-Net), its Sobolev term (if any) in jvp mode. Other families (a chunked plugin that is no diffusion
    policy, the MLPs) train each run alone instead of reaching for a U-Net they do not have."""
    return bool(getattr(cfg.policy_class, "stackable", False)) and (not cfg.uses_sobolev or cfg.sobolev.mode == "jvp")


def stack_key(task: str, cfg: TrainConfig) -> tuple:
    """Runs with equal keys are compatible (see the module docstring)."""
    s = cfg.sobolev
    return (task, cfg.method, tuple(sorted((k, str(v)) for k, v in cfg.architecture().items())),
            cfg.data.batch_size, s.mode, s.path, s.n_proj, s.fraction)


def _member_view(stacked: torch.Tensor, solo_dim: int, R: int, r: int) -> torch.Tensor:
    return stacked[r] if stacked.dim() == solo_dim + 1 else stacked.chunk(R, dim=0)[r]


class Stack:
    """R started runs (:func:`sdp_cli.train.start_run`) sharing one :class:`StackedUnet1D`."""

    def __init__(self, runs: list):
        from sdp_cli.policy.stacked_unet import StackedUnet1D

        self.runs = runs
        p = runs[0].cfg.policy
        d = runs[0].policy.dims
        self.R = len(runs)
        self.net = StackedUnet1D.from_members(
            [r.policy.unet for r in runs], action_dim=d["n_action"], cond_dim=d["n_xi"] + p.n_obs_steps * d["n_obs"],
            down_dims=p.down_dims, kernel_size=p.kernel_size, n_groups=p.n_groups,
            step_embed_dim=p.step_embed_dim).to(runs[0].device)
        self.links = []   # per member: [(solo parameter, stacked parameter)]
        for i, run in enumerate(runs):
            pairs = []
            for name, sp in run.policy.unet.named_parameters():
                stacked = self.net.net.get_parameter(name)
                sp.data = _member_view(stacked.data, sp.dim(), self.R, i)   # the solo weights live in the stack
                pairs.append((sp, stacked))
            self.links.append(pairs)
        self.optim = StackedOptimisation(runs, [stacked for _, stacked in self.links[0]])

    # ------------------------------------------------------------------ one step of every active member
    def _draw_and_inputs(self, run, batch: dict) -> dict:
        """Member inputs and random draws, in a solo step's order (noise, diffusion step, projections)."""
        pol, cfg = run.policy, run.cfg
        s, T_o, g = cfg.sobolev, pol.T_o, run.gen
        tau0, a_hist, obs, xi = batch["tau0"], batch["a_hist"], batch["obs"], batch["xi"]
        dev, B = tau0.device, tau0.shape[0]
        gdev = g.device
        noise = torch.randn(tau0.shape, generator=g, device=gdev).to(dev)
        k = torch.randint(0, pol.K, (B,), generator=g, device=gdev).to(dev)
        tau_k = pol.noise_scheduler.add_noise(tau0, noise, k)
        rest = tau_k[:, T_o:]
        m = {"B": B, "x": torch.cat([a_hist, rest], dim=1), "k": k, "cond": torch.cat([xi, obs.flatten(1)], -1),
             "target": tau0[:, T_o:], "projections": []}
        if not cfg.uses_sobolev:
            return m
        n_s = max(1, round(s.fraction * B))
        J = batch["jac"][:n_s, T_o:]
        m.update(n_s=n_s, J=J.reshape(n_s, -1, J.shape[-1]), w_cap=batch.get("sob_weight"))
        a_hist_jac = batch.get("a_hist_jac")
        rest_jac = None
        if s.path == "total":
            sab = pol.noise_scheduler.alphas_cumprod.to(dev)[k].sqrt().to(tau0.dtype)
            rest_jac = sab[:, None, None, None] * batch["jac"][:, T_o:]
        for _ in range(s.n_proj):
            w = random_unit((n_s, J.shape[-1]), g, dev, J.dtype)
            o_d, tau_d = chunk_tangents(w, batch["obs_jac"], a_hist, a_hist_jac, rest, rest_jac)
            cond_d = torch.cat([torch.zeros_like(xi[:n_s]), o_d.flatten(1)], dim=-1)
            m["projections"].append((w, cond_d, tau_d))
        return m

    @staticmethod
    def _pad(parts: list, n: int) -> torch.Tensor:
        """Stack member tensors ``(n_r, ...)`` into ``(n, R, ...)``, zero rows below each member's own."""
        ref = next(p for p in parts if p is not None)
        out = ref.new_zeros((n, len(parts), *ref.shape[1:]))
        for i, p in enumerate(parts):
            if p is not None:
                out[: p.shape[0], i] = p
        return out

    def losses(self, members: list) -> list:
        """``[(loss, parts) or None]`` per member (None: inactive) from :meth:`_draw_and_inputs`' dicts."""
        act = [m for m in members if m is not None]
        Bm = max(m["B"] for m in act)
        x = self._pad([m and m["x"] for m in members], Bm)
        k = self._pad([m and m["k"] for m in members], Bm)
        cond = self._pad([m and m["cond"] for m in members], Bm)
        T_o = self.runs[0].policy.T_o
        sob = self.runs[0].cfg.uses_sobolev
        terms = [0.0 for _ in members]
        if not sob:
            y = self.net(x, k, cond)
        else:
            n_max = max(m["n_s"] for m in act)
            for j in range(len(act[0]["projections"])):
                pr = [m and m["projections"][j] for m in members]
                cond_d = self._pad([p and p[1] for p in pr], n_max)
                tau_d = (self._pad([p and p[2] for p in pr], n_max) if any(p and p[2] is not None for p in pr)
                         else None)
                y, yd = self.net.forward_jvp(x, tau_d, k, cond, cond_d)
                for i, m in enumerate(members):
                    if m is None:
                        continue
                    n, w = m["n_s"], pr[i][0]
                    ydot = yd[:n, i, T_o:].reshape(n, -1)
                    target = torch.einsum("boi,bi->bo", m["J"], w)
                    terms[i] = terms[i] + ((target - ydot) ** 2).sum(-1)
        out = []
        for i, (m, run) in enumerate(zip(members, self.runs)):
            if m is None:
                out.append(None)
                continue
            pred = y[: m["B"], i, T_o:]
            dp = ((pred - m["target"]) ** 2).mean()
            if not sob:
                out.append((dp, {"dp": dp.detach(), "sobolev": torch.zeros((), device=dp.device)}))
                continue
            J = m["J"]
            term = terms[i] * (J.shape[-1] / J.shape[1]) / len(m["projections"])
            wc = m["w_cap"]
            s = run.policy.sobolev_scale * (term.mean() if wc is None else (wc[: m["n_s"]] * term).mean())
            out.append((dp + run.cfg.sobolev.weight * s, {"dp": dp.detach(), "sobolev": s.detach()}))
        return out

    def step(self) -> list:
        """One optimisation step of every active member: ``[(loss, parts, grad_norm) or None]``."""
        active = [not r.done for r in self.runs]
        members = [self._draw_and_inputs(r, r.next_batch()) if a else None for r, a in zip(self.runs, active)]
        results = self.losses(members)
        for run, res in zip(self.runs, results):
            if res is not None and not torch.isfinite(res[0]):
                raise SdpError(f"training diverged at step {run.step} of {run.out} (loss {res[0].item()}); "
                               "try a lower --lr or --sobolev-alpha")
        self.net.zero_grad(set_to_none=True)
        sum(res[0] for res in results if res is not None).backward()
        norms = self.optim.step(active)
        out = []
        for run, res, gnorm in zip(self.runs, results, norms):
            if res is None:
                out.append(None)
                continue
            run.sched.step()
            out.append((res[0], res[1], gnorm))
        return out

def train_stack(datas: list, outs: list, cfgs: list[TrainConfig], device: str = "cpu",
                log: Callable[[str], None] = print, on_step: Callable[[int], None] | None = None) -> list[Path]:
    """Train (or resume, where a run folder holds a checkpoint) compatible runs as one stack; returns their final
    checkpoints. One run alone is a stack of one (the solo trainer is :func:`sdp_cli.train.train`)."""
    from sdp_cli.interrupts import deferred
    from sdp_cli.train import _discard_if_failed_at_start, start_run

    if not cfgs:
        return []
    bad = [str(o) for o, c in zip(outs, cfgs) if not stackable(c)]
    if bad:
        raise SdpError(f"not stackable (a diffusion method with the Sobolev term in jvp mode, if any): {', '.join(bad)}")
    runs = [start_run(d, o, c, device, resume=(Path(o) / "checkpoint.pt").exists()) for d, o, c in zip(datas, outs, cfgs)]
    keys = {stack_key(r.base["task"], r.cfg) for r in runs}
    if len(keys) > 1:
        raise SdpError(f"runs {', '.join(map(str, outs))} cannot share a stack: they differ in task, method, "
                       "architecture, batch size or Sobolev settings")
    for run in runs:
        log(f"{run.out.name}: {run.describe()}")
        run.t0 = run.last_ck = time.perf_counter()
        run.policy.train()
    stack = Stack(runs)
    steps = 0
    with deferred() as interrupt, contextlib.ExitStack() as guards:
        for run in runs:
            guards.enter_context(_discard_if_failed_at_start(run.out, run.created, run.ck_path))
        while not all(r.done for r in runs):
            for run, res in zip(runs, stack.step()):
                if res is not None:
                    run.record(*res)
            steps += 1
            if on_step is not None:
                on_step(steps)
            interrupt.check(lambda: [r.save() for r in runs])   # Ctrl-C / SIGTERM: every member at a step boundary
    for run in runs:
        run.save()
        log(f"{run.out.name}: done, {run.step} steps, final loss "
            f"{run.metrics.rows[-1]['loss'] if run.metrics.rows else 'n/a'}")
    return [r.ck_path for r in runs]

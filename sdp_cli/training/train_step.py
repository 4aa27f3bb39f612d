"""One training step for one run and for a stack of runs (Algorithm 1, lines 17-21).

:func:`step` is the step of the trainer (``sdp train``, ``sdp loop``), of the stacked trainer (``sdp pipeline
--run``, :mod:`sdp_cli.training.train_stack`) and of the estimate's timing: every active run draws its batch, the family's
loss of each (its own draws from its own generator), a divergence check before any weight moves, one backward,
then each run's gradient-norm clipping, AdamW step, EMA update and LR schedule with its own settings. What differs
between one run and R runs is only *where the arithmetic runs*, a group:

- :class:`OneRun`: the policy's :meth:`~sdp_cli.policy.base.Policy.compute_loss` on its own network, then torch's
  ``clip_grad_norm_``, fused ``AdamW`` and diffusers' ``EMAModel`` over its parameter tensors;
- :class:`Stack`: a family that opts into stacking (``Policy.stackable``) gives ``Family.stack(policies)``, one
  network for R runs whose ``losses(draws)`` applies the family's own ``loss_from`` to each member's
  ``draw`` (:class:`sdp_cli.policy.diffusion.StackedDiffusion`); the members' clipping, AdamW and EMA run as
  whole-stack matrix operations (:class:`sdp_cli.training.stack_optim.StackedOptimisation`: the same formulas, torch's
  fused AdamW kernel on each member's row).

A run trained in a stack equals the same run trained alone to float32 rounding (the grouped kernels and the
gradient norm sum in another order: ``tests/test_train_stack.py``).
"""

from __future__ import annotations

import torch

from sdp_cli.errors import SdpError
from sdp_cli.training.stack_optim import StackedOptimisation


class Diverged(SdpError):
    """The loss of a training step is not finite (names the run's step and, in a stack, its folder)."""

    def __init__(self, loss: float, step: int, where: str = "", run=None):
        super().__init__(f"training diverged at step {step}{where} (loss {loss}); "
                         "try a lower --lr or --sobolev-alpha")
        self.loss, self.run = loss, run


class OneRun:
    """A run alone (``run``: :class:`sdp_cli.training.train.Run` or anything with its ``policy, cfg, opt, sched, ema,
    gen, done, next_batch()``)."""

    def __init__(self, run):
        self.runs = [run]

    def losses(self, batches: list) -> list:
        run = self.runs[0]
        return [run.policy.compute_loss(batches[0], run.gen)]

    def zero_grad(self) -> None:
        self.runs[0].opt.zero_grad(set_to_none=True)

    def optimise(self, active: list[bool]) -> list:
        run = self.runs[0]
        gnorm = torch.nn.utils.clip_grad_norm_(run.policy.parameters(), run.cfg.optim.grad_clip)
        run.opt.step()
        run.ema.step(run.policy.parameters())
        return [gnorm]


class Stack:
    """R started runs of one stackable family and architecture as one network (see the module docstring)."""

    def __init__(self, runs: list):
        self.runs = runs
        family = type(runs[0].policy)
        if not getattr(family, "stackable", False):
            raise SdpError(f"the {runs[0].cfg.method!r} family cannot train runs as one stack")
        self.module = family.stack([r.policy for r in runs])
        self.optim = StackedOptimisation(runs, self.module.parameters)

    def losses(self, batches: list) -> list:
        return self.module.losses([None if b is None else r.policy.draw(b, r.gen)
                                   for r, b in zip(self.runs, batches)])

    def zero_grad(self) -> None:
        self.module.zero_grad()

    def optimise(self, active: list[bool]) -> list:
        return list(self.optim.step(active))


def step(group) -> list:
    """One optimisation step of every active (not finished) run of ``group``: ``[(loss, parts, grad_norm) or
    None]`` per run; raises :class:`Diverged` before touching any weight when a loss is not finite. The runs'
    step counters are the caller's (:meth:`sdp_cli.training.train.Run.record`)."""
    runs = group.runs
    active = [not r.done for r in runs]
    results = group.losses([r.next_batch() if a else None for r, a in zip(runs, active)])
    for run, res in zip(runs, results):
        if res is not None and not torch.isfinite(res[0]):
            raise Diverged(res[0].item(), run.step, f" of {run.out}" if len(runs) > 1 else "", run)
    group.zero_grad()
    live = [res[0] for res in results if res is not None]
    (live[0] if len(live) == 1 else sum(live)).backward()
    norms = group.optimise(active)
    out = []
    for run, res, gnorm in zip(runs, results, norms):
        if res is None:
            out.append(None)
            continue
        if run.sched is not None:
            run.sched.step()
        out.append((res[0], res[1], gnorm))
    return out

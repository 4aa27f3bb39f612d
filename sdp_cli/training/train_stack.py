"""Many runs at once: train R compatible runs of a stackable family as one stacked network (``sdp pipeline --run``).

The paper's U-Net is tiny, so a step of one run is mostly per-op overhead; R runs stacked as one network cost
little more than one (``bench/stacked_train.py``). The step is the solo trainer's (:func:`sdp_cli.training.train_step.step`
with a :class:`sdp_cli.training.train_step.Stack`), and everything else of a run stays its own and is the solo trainer's
(:class:`sdp_cli.training.train.Run`): dataset, epoch order, random stream (the family's ``draw``, in a solo run's order),
normalizer and Sobolev scale, AdamW state, LR schedule, EMA, gradient clipping, ``save_at`` checkpoints, metrics
and checkpoints; a member's checkpoint is a solo checkpoint (``load_policy``, ``sdp train --resume``), and a
killed stack resumes every member.

A run trained in a stack equals the same run trained alone to float32 rounding (``tests/test_train_stack.py``),
whichever runs share its stack. Compatible runs (:func:`stack_key`): the same task, method, architecture (T_h,
T_o, K, action, U-Net), batch size, Sobolev mode, path, projections and fraction, and ``compile``; seeds, datasets (n_traj),
epochs, alpha, learning rates and the other optimisation settings may differ. Members whose batches are smaller
(a smaller dataset's last batch of an epoch, a finished run) are padded and their padded rows left out of their
losses; a finished member stays in the stack but takes no step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from sdp_cli.errors import SdpError
from sdp_cli.policy.config import TrainConfig

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
            cfg.data.batch_size, s.mode, s.path, s.n_proj, s.fraction, cfg.compile)


def train_stack(datas: list, outs: list, cfgs: list[TrainConfig], device: str = "cpu",
                log: Callable[[str], None] = print, on_step: Callable[[int], None] | None = None,
                inits: list | None = None, failed: dict | None = None) -> list[Path]:
    """Train (or resume, where a run folder holds a checkpoint) compatible runs as one stack; returns their final
    checkpoints. ``inits``: per run, a checkpoint to start from (``sdp train --init``: a loop's warm start) or
    None. ``failed``: a dict that collects ``{run folder: why}`` of runs whose loss diverged, which leave the
    stack while the others train on (their checkpoints are returned); without it a divergence stops the stack.
    One run alone is a stack of one (the solo trainer is :func:`sdp_cli.training.train.train`)."""
    from sdp_cli.training.train import drive, start_run
    from sdp_cli.training.train_step import Stack

    if not cfgs:
        return []
    bad = [str(o) for o, c in zip(outs, cfgs) if not stackable(c)]
    if bad:
        raise SdpError(f"not stackable (a diffusion method with the Sobolev term in jvp mode, if any): {', '.join(bad)}")
    inits = inits or [None] * len(cfgs)
    runs = [start_run(d, o, c, device, resume=(Path(o) / "checkpoint.pt").exists(), init=i)
            for d, o, c, i in zip(datas, outs, cfgs, inits)]
    keys = {stack_key(r.base["task"], r.cfg) for r in runs}
    if len(keys) > 1:
        raise SdpError(f"runs {', '.join(map(str, outs))} cannot share a stack: they differ in task, method, "
                       "architecture, batch size or Sobolev settings")
    for run in runs:
        log(f"{run.out.name}: {run.describe()}")
    drive(Stack(runs), on_step, regroup=Stack if failed is not None else None, failed=failed)
    runs = [r for r in runs if r.out not in (failed or {})]
    for run in runs:
        log(f"{run.out.name}: done, {run.step} steps, final loss "
            f"{run.metrics.rows[-1]['loss'] if run.metrics.rows else 'n/a'}")
    return [r.ck_path for r in runs]

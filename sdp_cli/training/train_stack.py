"""Many runs at once: train R compatible runs of a stackable family as one stacked network (``sdp pipeline --run``).

The paper's U-Net is tiny, so a step of one run is mostly per-op overhead; R runs stacked as one network cost
little more than one (``bench/stacked_train.py``). The step is the solo trainer's (:func:`sdp_cli.training.train_step.step`
with a :class:`sdp_cli.training.train_step.Stack`), and everything else of a run stays its own and is the solo trainer's
(:class:`sdp_cli.training.train.Run`): dataset, epoch order, random stream (the family's ``draw``, in a solo run's order),
normalizer and Sobolev scale, AdamW state, LR schedule, EMA, gradient clipping, ``save_at`` checkpoints, metrics
and checkpoints; a member's checkpoint is a solo checkpoint (``load_policy``, ``sdp train --resume``), and a
killed stack resumes every member.

A run trained in a stack equals the same run trained alone to float32 rounding (``tests/test_train_stack.py``),
whichever runs share its stack. Compatible runs (:func:`stack_key`) are keyed by what the stacked network's shape
needs: the family, the network's sizes on the run's task (input, output and tangent dimensions:
``Policy.dims_for``), the architecture (T_h, T_o, K, action, U-Net), the batch size and ``compile``. Members may
differ in method (each applies its own loss: SDP and DP in one stack, the DP members' tangent rows zero and
unused), Sobolev settings (projections, fraction, path; the mode is jvp), task variant, dataset, seed, epochs,
alpha, learning rates and the other optimisation settings, and (in a loop) T_a. Members whose batches are
smaller (a smaller dataset's last batch of an epoch, a finished run) are padded and their padded rows left out
of their losses; a finished member stays in the stack but takes no step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from sdp_cli.errors import SdpError
from sdp_cli.policy.config import TrainConfig
from sdp_cli.tasks import get_task

#: the default number of runs per stack (fixed, not chosen by the machine: same seed, same bytes on every machine
#: with torch's CPU kernels capped: sdp_cli/kernels.py)
DEFAULT_STACK = 8


def stackable(cfg: TrainConfig) -> bool:
    """Runs of this config can share a stack: the method's family opts in (``Policy.stackable``: the diffusion
    U-Net), its Sobolev term (if any) in jvp mode. Other families (a chunked plugin that is no diffusion
    policy, the MLPs) train each run alone instead of reaching for a U-Net they do not have."""
    return bool(getattr(cfg.policy_class, "stackable", False)) and (not cfg.uses_sobolev or cfg.sobolev.mode == "jvp")


def network_dims(task, cfg: TrainConfig) -> dict:
    """The network's sizes ``{n_action, n_obs, n_xi, ndx}`` for runs of ``cfg`` on ``task`` (a name or a task)."""
    task = get_task(task) if isinstance(task, str) else task
    family = cfg.policy_class
    return family.dims_for(cfg, task, family.action_for(cfg, task))


def stack_key(task, cfg: TrainConfig, *, dims: dict | None = None) -> tuple:
    """Runs of a stackable config with equal keys are compatible (see the module docstring); ``dims``: the
    network's sizes if known (a started run's), else :func:`network_dims` of ``task``."""
    dims = network_dims(task, cfg) if dims is None else dims
    return (cfg.policy_class.__module__, cfg.policy_class.__qualname__, tuple(sorted(dims.items())),
            tuple(sorted((k, str(v)) for k, v in cfg.architecture().items() if k != "method")),
            cfg.data.batch_size, cfg.compile)


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
    keys = {stack_key(r.base["task"], r.cfg, dims=r.base["dims"]) for r in runs}
    if len(keys) > 1:
        raise SdpError(f"runs {', '.join(map(str, outs))} cannot share a stack: they differ in family, network "
                       "sizes, architecture, batch size or compile")
    for run in runs:
        log(f"{run.out.name}: {run.describe()}")
    drive(Stack(runs), on_step, regroup=Stack if failed is not None else None, failed=failed)
    runs = [r for r in runs if r.out not in (failed or {})]
    for run in runs:
        log(f"{run.out.name}: done, {run.step} steps, final loss "
            f"{run.metrics.rows[-1]['loss'] if run.metrics.rows else 'n/a'}")
    return [r.ck_path for r in runs]

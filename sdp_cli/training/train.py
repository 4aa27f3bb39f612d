"""``sdp train``: fit SDP, DP, PDDP or PDDP+S on a dataset artifact (Algorithm 1, lines 11-23).

- Epochs follow the paper: ``E = |D| (T - T_h) / T_h`` chunks for diffusion policies,
  ``|D| T`` pairs for the MLPs; one epoch draws ``E`` samples without replacement and
  trains ``ceil(E / B)`` steps on them, the last batch smaller (:mod:`sdp_cli.data.sampling`).
- AdamW, cosine learning rate with linear warm-up, EMA of the weights (diffusers'
  ``EMAModel`` with warm-up, power 0.75, as diffusion policy), gradient-norm clipping.
- Run folder ``--out``: ``checkpoint.pt`` (latest; rewritten atomically every
  ``checkpoint_every_s`` seconds, at the end and on Ctrl-C), ``epoch_<E>.pt`` for each
  ``--save-at`` epoch, ``metrics.csv`` (step, epoch, loss, dp, sobolev, lr, grad_norm). Clock
  readings stay out of the folder (a DVC output: same seed, same bytes): the training wall time
  is in the sidecar ``<out>.timing.json`` next to it (:func:`sdp_cli.data.artifacts.save_timing`).
- ``resume=True`` continues from ``checkpoint.pt`` bit-for-bit (optimizer, schedule, EMA
  and RNG state are restored). ``init`` starts from another checkpoint's weights and EMA
  (the alternating loop's warm start); its architecture settings win, and its normalizer is
  widened to cover the new dataset too (:meth:`Normalizer.union`).
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Callable
import shutil

import torch

from sdp_cli.data.chunks import fit_normalizer, load_dataset, task_options_of
from sdp_cli.errors import SdpError
from sdp_cli.data.artifacts import artifact_writes, ensure_dir, load_timing, portable_path, save_timing
from sdp_cli.data.metrics_log import MetricsLog
from sdp_cli.data.sampling import epoch_indices, steps_per_epoch as epoch_steps
from sdp_cli.policy.checkpoint import CHECKPOINT_NAME, file_sha256, load_checkpoint, save_checkpoint
from sdp_cli.policy.config import TrainConfig, resolved_alpha
from sdp_cli.policy.registry import make_policy
from sdp_cli.execution.interrupts import deferred



def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise SdpError(f"invalid device {device!r} (use auto, cpu, cuda, cuda:0)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SdpError("--device cuda requested but CUDA is not available")
    return dev


def sobolev_scale_of(policy, tensors: dict) -> float:
    """The Sobolev term's factor on this dataset: :func:`balance_scale` (``sobolev_balance``) or 1."""
    cfg = policy.config
    if not (cfg.uses_sobolev and cfg.sobolev.balance):
        return 1.0
    from sdp_cli.losses.sobolev import balance_scale

    return balance_scale(*policy.balance_terms(tensors))


def prepare(cfg: TrainConfig, task, arrays, normalizer=None, device="cpu", widen: bool = False):
    """``(policy, tensors, epoch_size, action, dims)``: the method's policy object with a fitted (or given)
    normalizer and its Sobolev scale set; ``widen``: the given normalizer's ranges are extended to cover this
    dataset (``--init``)."""
    cls = cfg.policy_class
    ds, action = cls.make_dataset(cfg, task, arrays, cfg.uses_sobolev)
    dims = cls.dims_for(cfg, task, action)
    policy = make_policy(cfg, dims)
    norm = fit_normalizer(task, arrays, action) if normalizer is None or widen else normalizer
    if normalizer is not None and widen:
        norm = normalizer.union(norm)
    policy.normalizer.load_state_dict(norm.state_dict())
    tensors = ds.tensors(policy.normalizer, device)
    if cfg.uses_sobolev and cfg.sobolev.cap is not None:
        from sdp_cli.losses.sobolev import capped_weights

        tensors["sob_weight"] = capped_weights(tensors["jac"][:, cfg.policy.n_obs_steps:], cfg.sobolev.cap)
    policy.sobolev_scale = sobolev_scale_of(policy, tensors)
    return policy.to(device), tensors, ds.epoch_size(), action, dims


def reconcile_config(cfg: TrainConfig, ck_path: Path, resume: bool, init) -> tuple[TrainConfig, dict | None,
                                                                                  dict | None]:
    """``(cfg, prev, init_ck)``: the config a run trains with. ``--resume``: the run's own (other settings are
    refused, ``sobolev_alpha`` None means the task's default); ``--init``: the init checkpoint's
    architecture (the ``policy`` section) wins. ``prev`` / ``init_ck`` are the loaded checkpoints (or None)."""
    out = ck_path.parent
    if out.exists() and not out.is_dir():
        raise SdpError(f"--out {out} exists and is not a folder")
    prev = None
    if resume and not ck_path.exists():
        raise SdpError(f"--resume: {out} holds no run to resume (no {ck_path.name}); drop --resume to start one")
    if ck_path.exists():
        if not resume:
            raise SdpError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
        prev = load_checkpoint(ck_path)
        stored = TrainConfig.from_dict(prev["config"])
        if stored.method != cfg.method:
            raise SdpError(f"cannot resume: {ck_path} is a {stored.method!r} run, not {cfg.method!r}")
        skip = {"checkpoint_every_s"} | (set(stored.architecture()) if prev.get("init") else set())  # --init's win
        old_d, new_d = stored.options(), cfg.options()
        changed = [f"{k}={new_d[k]!r} (run: {old_d[k]!r})" for k in old_d if k not in skip and old_d[k] != new_d[k]
                   and not (k == "sobolev_alpha" and new_d[k] is None)]   # None: the task's default
        if changed:
            raise SdpError(f"cannot resume {ck_path} with other settings: {', '.join(changed)}; resume with the "
                           f"run's options or train into another --out")
        cfg = stored
    init_ck = None
    if init is not None and prev is None:
        init_ck = load_checkpoint(init)
        init_cfg = TrainConfig.from_dict(init_ck["config"])
        if init_cfg.method != cfg.method:
            raise SdpError(f"--init checkpoint is a {init_cfg.method!r} policy, not {cfg.method!r}")
        cfg = cfg.with_options(**init_cfg.architecture())
    return cfg, prev, init_ck


def _load_data(data, cfg: TrainConfig, prev: dict | None, init_ck: dict | None, ck_path: Path):
    """``(arrays, meta, task, sha256)`` of the dataset, checked against the resumed run / init checkpoint."""
    ref_task = (prev or init_ck or {}).get("task")
    arrays, meta, task = load_dataset(data, require_gains=cfg.uses_sobolev, task_name=ref_task)
    fingerprint = file_sha256(data)
    for ref, what in ((prev, "resumed run"), (init_ck, "--init checkpoint")):
        if ref is not None and ref["task"] != meta["task"]:
            raise SdpError(f"dataset task {meta['task']!r} does not match the {what}'s task {ref['task']!r}")
    if prev is not None and prev["dataset"]["sha256"] != fingerprint:
        raise SdpError(f"cannot resume: {data} is not the dataset {ck_path} was trained on")
    return arrays, meta, task, fingerprint


def optimizer_for(cfg: TrainConfig, params) -> torch.optim.AdamW:
    """The run's AdamW; torch's fused kernel: one pass over each of the ~200 tensors (foreach: several passes,
    4x the time on a CPU: ``bench/profile_step.py``)."""
    o = cfg.optim
    return torch.optim.AdamW(params, lr=o.lr, betas=tuple(o.betas), weight_decay=o.weight_decay, fused=True)


def ema_for(cfg: TrainConfig, params):
    """The run's EMA of the weights (diffusers' ``EMAModel`` with diffusion policy's warm-up)."""
    from diffusers.training_utils import EMAModel

    o = cfg.optim
    return EMAModel(params, decay=o.ema_max_decay, use_ema_warmup=True, inv_gamma=1.0, power=o.ema_power,
                    foreach=True)


def _optimisation(cfg: TrainConfig, policy, total: int, init_ck: dict | None, fitted_norm: dict):
    """``(opt, lr_scheduler, ema, generator)``: AdamW, cosine schedule with warm-up, EMA (diffusion policy's
    settings), the batch/noise generator; ``--init`` loads the init checkpoint's weights and EMA."""
    from diffusers.optimization import get_scheduler

    o = cfg.optim
    warmup = o.warmup_steps if o.warmup_steps is not None else min(500, total // 10)
    opt = optimizer_for(cfg, policy.parameters())
    sched = get_scheduler("cosine", opt, num_warmup_steps=warmup, num_training_steps=total)
    gen = torch.Generator().manual_seed(cfg.seed)   # CPU: the same draws on CPU and GPU
    if init_ck is not None:
        policy.load_state_dict(init_ck["ema_model"] or init_ck["model"])
    ema = ema_for(cfg, policy.parameters())
    if init_ck is not None:
        policy.load_state_dict(init_ck["model"])
        policy.normalizer.load_state_dict(fitted_norm)   # the widened one, not the checkpoint's
    return opt, sched, ema, gen


def _restore(prev: dict, policy, opt, sched, ema, gen, dev, ck_path: Path, out: Path) -> tuple[int, float]:
    """``--resume``: weights, optimizer, schedule, EMA and random state of the checkpoint; ``(step, wall0)``."""
    policy.load_state_dict(prev["model"])
    ts = prev["train_state"]
    opt.load_state_dict(ts["optimizer"])
    sched.load_state_dict(ts["lr_scheduler"])
    ema.load_state_dict(ts["ema"])
    ema.to(dev)  # the checkpoint is loaded on the CPU; EMA updates need the weights' device
    try:
        gen.set_state(ts["generator"].cpu())
    except RuntimeError:
        raise SdpError(f"cannot resume {ck_path} on {dev}: it was trained on another device type "
                       "(its random state does not carry over); resume with the same --device") from None
    return int(prev["step"]), float(ts.get("wall_time", load_timing(out).get("wall_time", 0.0)))


class Run:
    """One training run's state between steps: config, policy, data tensors, optimisation, metrics and step
    counter, with its checkpoints (:meth:`save`). :func:`drive` steps one alone (:func:`train`) or several as one
    stack (:mod:`sdp_cli.training.train_stack`) with the same objects and the same step (:func:`sdp_cli.training.train_step.step`),
    so a stacked run's checkpoints, metrics and resume are a solo run's. :func:`start_run` builds one."""

    def __init__(self, **kw):
        self.__dict__.update(kw)
        self.order, self.order_epoch = None, -1
        self.t0 = self.last_ck = time.perf_counter()

    def next_batch(self) -> dict:
        """This step's batch: the ``j``-th slice of the epoch's ``E`` samples drawn without replacement."""
        epoch, j = divmod(self.step, self.steps_per_epoch)
        if epoch != self.order_epoch:   # this epoch's E samples, without replacement
            self.order = epoch_indices(self.n_samples, self.E, self.cfg.seed, epoch).to(self.device)
            self.order_epoch = epoch
        B = self.cfg.data.batch_size
        idx = self.order[j * B:(j + 1) * B]
        return {k: v[idx] for k, v in self.tensors.items()}

    @property
    def done(self) -> bool:
        return self.step >= self.total

    def record(self, loss, parts, gnorm) -> dict:
        """After a step: count it, log its metrics row, keep the ``save_at`` checkpoint and the periodic one."""
        self.step += 1
        row = self.metrics.add(self.step, self.steps_per_epoch, loss, parts, self.sched.get_last_lr()[0], gnorm)
        epoch = self.step // self.steps_per_epoch
        if self.step % self.steps_per_epoch == 0 and epoch in self.cfg.save_at:
            self.save(self.out / f"epoch_{epoch}.pt", with_state=False)
        if not self.done and time.perf_counter() - self.last_ck >= self.cfg.checkpoint_every_s:
            self.save()
            self.last_ck = time.perf_counter()
        return row

    def save(self, path: Path | None = None, with_state: bool = True) -> None:
        """A checkpoint (the run's ``checkpoint.pt`` by default): weights, EMA weights and, ``with_state``, the
        optimizer, schedule, EMA and random state for ``--resume``; the metrics file with it."""
        policy, ema = self.policy, self.ema
        ema.store(policy.parameters())
        ema.copy_to(policy.parameters())
        ema_sd = {k: v.detach().clone().cpu() for k, v in policy.state_dict().items()}
        ema.restore(policy.parameters())
        payload = {**self.base, "epoch": self.step // self.steps_per_epoch, "step": self.step, "finished": self.done,
                   "model": {k: v.detach().cpu() for k, v in policy.state_dict().items()}, "ema_model": ema_sd,
                   "train_state": None}
        if with_state:
            payload["train_state"] = {"optimizer": self.opt.state_dict(), "lr_scheduler": self.sched.state_dict(),
                                      "ema": ema.state_dict(), "generator": self.gen.get_state()}
        # the metrics first: a kill between the two writes leaves metrics.csv ahead of the checkpoint (--resume
        # drops the rows past its step), never behind it (rows lost for good)
        with artifact_writes():   # metrics, checkpoint and timing: all three or (a full disk) none
            self._write(path, payload, with_state)

    def _write(self, path: Path | None, payload: dict, with_state: bool) -> None:
        self.metrics.rewrite()
        save_checkpoint(path or self.ck_path, payload)
        if with_state:
            save_timing(self.out, {"wall_time": self.wall0 + (time.perf_counter() - self.t0), "step": self.step,
                                   "device": str(self.device)}, artifact=path or self.ck_path)

    def describe(self) -> str:
        cfg, B = self.cfg, self.cfg.data.batch_size
        n_params = sum(p.numel() for p in self.policy.parameters())
        return (f"{cfg.method}: {self.n_traj} trajectories, {self.n_samples} samples, epoch = {self.E} samples = "
                f"{self.steps_per_epoch} step(s) of <= {min(B, self.E)} (batch size {B}, drawn without "
                f"replacement); {cfg.data.epochs} epochs = {self.total} steps; "
                f"{n_params} parameters; device {self.device}" +
                (f"; alpha_Sobolev {cfg.sobolev.alpha:g} x balance {self.policy.sobolev_scale:.3g}"
                 if cfg.uses_sobolev else "") +
                (f"; resuming at step {self.step}" if self.resumed else "") +
                ("; --init's architecture replaces " + ", ".join(f"{k} {a!r} by {b!r}" for k, (a, b) in
                                                                  self.overridden.items())
                 if self.overridden else ""))


def start_run(data: str | Path, out: str | Path, cfg: TrainConfig, device: str = "auto", resume: bool = False,
              init: str | Path | None = None) -> Run:
    """A run ready for its first (or next, ``resume``) step: config reconciled, data loaded, policy built (the
    global torch seed set to the run's seed first), optimisation set up or restored; the run folder exists."""
    dev = resolve_device(device)
    out = Path(out)
    ck_path = out / CHECKPOINT_NAME
    asked = cfg.architecture()
    cfg, prev, init_ck = reconcile_config(cfg, ck_path, resume, init)
    # --init imposes its architecture: say which asked-for settings it replaced (describe())
    got = cfg.architecture()
    overridden = {k: (v, got[k]) for k, v in asked.items() if init_ck is not None and got[k] != v}
    arrays, meta, task, fingerprint = _load_data(data, cfg, prev, init_ck, ck_path)
    cfg = resolved_alpha(cfg, task)
    torch.manual_seed(cfg.seed)
    norm = None
    if init_ck is not None or prev is not None:
        from sdp_cli.policy.checkpoint import policy_from_checkpoint
        norm = policy_from_checkpoint(prev or init_ck).normalizer
    # --init: the previous normalizer, widened to the new dataset's ranges; --resume: kept as is
    policy, tensors, E, action, dims = prepare(cfg, task, arrays, norm, dev, widen=init_ck is not None)
    if cfg.compile:   # the training calls compiled (their first call compiles; TrainConfig.compile)
        policy.compile_network()
    fitted_norm = {k: v.clone() for k, v in policy.normalizer.state_dict().items()}
    n_samples = next(iter(tensors.values())).shape[0]
    steps_per_epoch = epoch_steps(E, cfg.data.batch_size)
    total = cfg.data.epochs * steps_per_epoch
    opt, sched, ema, gen = _optimisation(cfg, policy, total, init_ck, fitted_norm)
    step, wall0 = 0, 0.0
    if prev is not None:
        step, wall0 = _restore(prev, policy, opt, sched, ema, gen, dev, ck_path, out)
    rows = MetricsLog.read(out / "metrics.csv", step) if prev is not None else []
    created = not out.exists()
    ensure_dir(out, "run folder")
    base = {"method": cfg.method, "config": cfg.to_dict(), "dims": dims, "action": action,
            "task": meta["task"], "task_options": task_options_of(meta), "task_params": meta.get("task_params"),
            # paths relative to the checkpoint folder: the same bytes in any clone
            "dataset": {"path": portable_path(data, out), "sha256": fingerprint, "n_traj": int(len(arrays["X"])),
                        "T": int(task.T)},
            "init": portable_path(init, out) if init is not None else (prev or {}).get("init"),
            "steps_per_epoch": steps_per_epoch, "total_steps": total, "device": str(dev),
            "sobolev_scale": policy.sobolev_scale}
    return Run(cfg=cfg, out=out, ck_path=ck_path, device=dev, policy=policy, tensors=tensors, E=E,
               n_samples=n_samples, n_traj=len(arrays["X"]), steps_per_epoch=steps_per_epoch, total=total, opt=opt,
               sched=sched, ema=ema, gen=gen, step=step, wall0=wall0, resumed=prev is not None, created=created,
               overridden=overridden,
               base=base, metrics=MetricsLog(out / "metrics.csv", rows, resumed=prev is not None))


def train(data: str | Path, out: str | Path, cfg: TrainConfig, device: str = "auto", resume: bool = False,
          init: str | Path | None = None, progress: bool = True, log: Callable[[str], None] = print,
          on_step: Callable[[int], None] | None = None) -> Path:
    """Train and return the path of the final checkpoint (see the module docstring): :func:`start_run`, then
    :func:`drive` of the run alone (:class:`sdp_cli.training.train_step.OneRun`) until its last step, checkpointing on
    Ctrl-C / SIGTERM at a step boundary."""
    from sdp_cli.training.train_step import OneRun

    run = start_run(data, out, cfg, device, resume, init)
    log(run.describe())
    bar = _progress(progress)
    with bar:
        task_id = bar.add_task(run.cfg.method, total=run.total, completed=run.step, info="")

        def show(run, row):
            if run.step % 10 == 0 or run.done:
                bar.update(task_id, completed=run.step, info=f"loss {row['loss']} dp {row['dp']} "
                                                             f"sob {row['sobolev']} lr {row['lr']}")

        drive(OneRun(run), on_step, show)
    log(f"done: {run.step} steps, final loss {run.metrics.rows[-1]['loss'] if run.metrics.rows else 'n/a'}, "
        f"{time.perf_counter() - run.t0:.1f} s; checkpoint {run.ck_path}")
    return run.ck_path


def drive(group, on_step: Callable[[int], None] | None = None,
          on_row: Callable[[Run, dict], None] | None = None, regroup: Callable[[list], object] | None = None,
          failed: dict | None = None) -> None:
    """Step the runs of ``group`` (:mod:`sdp_cli.training.train_step`: one run alone or a stack) until every one is done,
    recording each run's metrics and checkpoints; ``on_step(step)`` after each step (the furthest run's step),
    ``on_row(run, row)`` after each run's metrics row. Ctrl-C / SIGTERM saves every run at a step boundary; a
    fresh run that fails before its first checkpoint leaves no folder; each run's final checkpoint at the end.

    ``regroup`` (a stack): a run whose loss diverges leaves the group, ``failed[run.out]`` says why (its folder
    keeps its last checkpoint, or goes if it has none and this call made it), and the others go on in
    ``regroup(their runs)``; without it a divergence stops every run."""
    from sdp_cli.training.train_step import Diverged, step

    runs = list(group.runs)
    for run in runs:
        run.t0 = run.last_ck = time.perf_counter()
        run.policy.train()
    with deferred() as interrupt, contextlib.ExitStack() as guards:
        for run in runs:
            guards.enter_context(_discard_if_failed_at_start(run.out, run.created, run.ck_path))
        while not all(r.done for r in group.runs):
            gens = [r.gen.get_state() for r in runs] if regroup is not None else None
            try:
                results = step(group)
            except Diverged as e:
                if regroup is None or e.run is None or len(group.runs) == 1:
                    raise
                failed[e.run.out] = str(e)
                for r, g in zip(runs, gens):   # the others redo this step with its draws
                    r.gen.set_state(g)
                runs.remove(e.run)
                if e.run.created and not e.run.ck_path.exists():
                    shutil.rmtree(e.run.out, ignore_errors=True)
                group = regroup(runs)
                continue
            for run, res in zip(group.runs, results):
                if res is not None:
                    row = run.record(*res)
                    if on_row is not None:
                        on_row(run, row)
            if on_step is not None:
                on_step(max(r.step for r in runs))
            interrupt.check(lambda: [r.save() for r in runs])   # stop at this step boundary
        for run in runs:   # a fresh run whose only checkpoint cannot be written (a full disk) leaves no folder
            run.save()


@contextlib.contextmanager
def _discard_if_failed_at_start(out: Path, created: bool, ck_path: Path):
    """A fresh run that fails before its first checkpoint (``--lr 1e30`` diverges at once) leaves no folder
    behind: only what this call created, and only while it holds no checkpoint."""
    try:
        yield
    except SdpError:
        if created and not ck_path.exists():
            shutil.rmtree(out, ignore_errors=True)
        raise


def _progress(enabled: bool):
    from sdp_cli.progress import enabled as progress_enabled
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeRemainingColumn(), TextColumn("{task.fields[info]}"),
                    console=Console(stderr=True), disable=not progress_enabled(enabled),
                    transient=False)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: sdp train")

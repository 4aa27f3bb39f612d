"""``sdp pipeline NAME --estimate``: what an experiment will cost, before it runs; writes nothing.

Per run (one task x method x seed x n_traj of the experiment, all its iterations):

- training: the steps of every iteration, ``epochs * ceil(E / B)`` with ``E = n_traj (T - T_h) / T_h``
  chunks (``n_traj T`` pairs for the MLPs) and ``B = min(batch_size, E)`` samples per step, as
  ``sdp train`` runs them (:mod:`sdp_cli.data.sampling`); the time per step is **measured** on this
  machine in CPU time (one torch thread, the real loss, backward, clipping, AdamW and EMA on a batch of the
  task's shapes), at the smallest and largest batch the experiment uses, linear in between;
- trajectory optimization: collection (``n_traj`` solves at iteration 0, ``2 n_traj`` after: from
  the policy's guess and from the naive guess, ArgminCost), the test-set refinements
  (two solves per test instance: from the policy's guess and alone, four with
  ``single_shooting``); per-solve times are reference means from ``results/tasks/TO_alone.md``
  (fatrop multiple shooting and ipopt single shooting from the naive guess, 2-core x86_64), not
  measured here, since compiling a task's optimizer can itself take minutes;
- rollouts: ``ceil(T / T_a) * K`` network evaluations on the test batch (a forward costs about a
  third of a training step).

The timed steps are bounded by ``budget_s`` (default 60 s); a compiled configuration also pays its compile once
per network shape (minutes with a cold inductor cache: 38 min for fig1's 50 quadrotor SDP/DP runs on 2 shared
cores, 2026-12-06; seconds with a warm one). Totals are given for one process and for
``workers`` processes (the sum divided by ``workers``, but never less than the longest run, whose
iterations depend on each other).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import torch

from sdp_cli.families import DEFAULT_TO
from sdp_cli.errors import SdpError
from sdp_cli.policy.registry import get_method
from sdp_cli.tasks import get_task
from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.registry import make_policy
from sdp_cli.training.train_stack import DEFAULT_STACK, network_dims


def to_reference(task: str, to: str = DEFAULT_TO) -> tuple[float, float]:
    """Reference seconds per solve of ``task``: (the loop's TO, single shooting); the loop's TO is multiple
    shooting (:attr:`Task.reference_solve_s`) or, ``to="ddp"``, box-FDDP where the task gives its time
    (:attr:`Task.reference_ddp_s`)."""
    t = get_task(task)
    ms, ss = t.reference_solve_s
    return ((t.reference_ddp_s or ms) if to == "ddp" else ms), ss


@dataclass
class TrainStage:
    run: str
    iteration: int
    task: str
    method: str
    T_h: int
    n_traj: int
    epochs: int
    batch_size: int
    action: str | None
    E: int = 0
    B: int = 0
    steps: int = 0
    #: the run's training config (architecture and Sobolev settings: what a step's time depends on)
    train: object = None

    @property
    def key(self) -> tuple:
        """What a step's measured time depends on besides the batch size: task, method, T_h, action and the
        run's architecture and Sobolev settings (a smaller U-Net or ``sobolev_fraction`` is another step); not
        K, the scheduler's length (a training step calls the network once whatever K)."""
        t = self.train
        arch = {k: v for k, v in t.architecture().items() if k != "diffusion_steps"} if t is not None else {}
        cfg = () if t is None else (tuple(sorted((k, str(v)) for k, v in arch.items())),
                                    str(t.sobolev.mode), str(t.sobolev.path), t.sobolev.n_proj, t.sobolev.fraction)
        return (self.task, self.method, self.T_h, self.action, cfg)


def training_stages(runs: dict) -> list[TrainStage]:
    """One :class:`TrainStage` per run and iteration of an experiment (``{run: LoopConfig}``, from
    :func:`sdp_cli.experiments.pipeline.loop_configs`), with its sizes."""
    from sdp_cli.data.sampling import steps_per_epoch

    out = []
    for run, cfg in runs.items():
        task = get_task(cfg.task)
        for k in range(cfg.n_algo):
            st = TrainStage(run, k, cfg.task, cfg.method, int(cfg.horizon), cfg.n_traj_at(k), int(cfg.epochs),
                            int(cfg.train.data.batch_size), cfg.train.policy.action, train=cfg.train)
            if get_method(st.method).chunked:
                st.E = max(1, math.ceil(st.n_traj * (task.T - st.T_h) / st.T_h))
            else:
                st.E = st.n_traj * task.T
            st.B = min(st.batch_size, st.E)
            st.steps = st.epochs * steps_per_epoch(st.E, st.batch_size)
            out.append(st)
    return out


def _synthetic_batch(method: str, dims: dict, T_h: int, B: int, gen: torch.Generator, device, T_o: int = 1) -> dict:
    r = lambda *s: (torch.rand(*s, generator=gen) * 2 - 1).to(device)
    A, n_o, n_xi, ndx = dims["n_action"], dims["n_obs"], dims["n_xi"], dims["ndx"]
    if get_method(method).chunked:
        b = {"tau0": r(B, T_h, A), "obs": r(B, T_o, n_o), "obs_jac": r(B, T_o, n_o, ndx), "xi": r(B, n_xi),
             "jac": r(B, T_h, A, ndx)}
        b["a_hist"] = b["tau0"][:, :T_o]
        return b
    return {"obs": r(B, n_o), "obs_jac": r(B, n_o, ndx), "u": r(B, A), "xi": r(B, n_xi), "jac": r(B, A, ndx)}


def _config(method: str, T_h: int, B: int, action: str | None, train=None):
    """The config a step is timed with: the run's (``train``) at batch size ``B``, or the method's defaults."""
    if train is not None:
        return train.with_options(batch_size=B)
    return TrainConfig.of(method=method, horizon=T_h, batch_size=B, action=action)


def _timed_runs(members: list[tuple], B: int, device) -> list:
    """One run per ``(task, method, T_h, action, train)`` of ``members``, as the trainer holds it (policy, AdamW,
    EMA, CPU generator; no LR schedule: a scalar update), each stepping its own synthetic batch of ``B``
    samples; run ``r`` seeded ``r``. A stack's members may differ in method, task and Sobolev settings."""
    from sdp_cli.training.train import ema_for, optimizer_for

    runs = []
    for r, (task_name, method, T_h, action, train) in enumerate(members):
        cfg = _config(method, T_h, B, action, train)
        dims = network_dims(task_name, cfg)
        torch.manual_seed(r)
        pol = make_policy(cfg, dims).to(device)
        gen = torch.Generator().manual_seed(r)
        batch = _synthetic_batch(method, dims, T_h, B, gen, device, cfg.policy.n_obs_steps)
        opt = optimizer_for(cfg, pol.parameters())
        runs.append(SimpleNamespace(policy=pol, cfg=cfg, gen=gen, opt=opt, ema=ema_for(cfg, pol.parameters()),
                                    sched=None, done=False, step=0, device=torch.device(device),
                                    next_batch=(lambda b=batch: b)))
    return runs


def _step_of(group):
    """One trainer step of ``group`` (:func:`sdp_cli.training.train_step.step`), its losses read as a metrics row does
    (a device sync on CUDA)."""
    from sdp_cli.training.train_step import step as train_step

    def step():
        for loss, _, _ in train_step(group):
            loss.detach().item()

    return step


def step_seconds(task_name: str, method: str, T_h: int, B: int, action: str | None = None, device="cpu",
                 max_s: float = 5.0, train=None, first: list | None = None) -> float:
    """Measured seconds of one training step (:func:`sdp_cli.training.train_step.step` of one run: loss, backward,
    clipping, AdamW, EMA); median of the steps that fit in ``max_s`` (at least 2, after one warm-up step);
    ``train``: the run's config (else the method's defaults at ``T_h``); ``first``: gets the warm-up step's
    seconds (a compiled config's compile)."""
    from sdp_cli.training.train_step import OneRun

    (run,) = _timed_runs([(task_name, method, T_h, action, train)], B, device)
    if run.cfg.compile:      # as the trainer does (its first step compiles: the warm-up, ``first``)
        run.policy.compile_network()
    return _median_seconds(_step_of(OneRun(run)), max_s, device, first)


def calibrate(train: list[TrainStage], device="cpu", budget_s: float = 60.0,
              log=lambda s: None) -> dict:
    """``{TrainStage.key: (B_lo, t_lo, B_hi, t_hi)}`` measured step times, and ``{("compile", key): seconds}``: a
    compiled config's first step, its compile as this machine's cache has it (cold: minutes; warm: seconds),
    charged once per training stage."""
    combos: dict = {}
    stage = {}
    for st in train:
        combos.setdefault(st.key, set()).add(st.B)
        stage.setdefault(st.key, st)
    n_meas = sum(min(2, len(bs)) for bs in combos.values())
    per = max(0.2, 0.8 * budget_s / max(n_meas, 1) - 0.3)
    out = {}
    for key, bs in combos.items():
        lo, hi = min(bs), max(bs)
        first = [] if stage[key].train is not None and stage[key].train.compile else None
        t_lo = step_seconds(*key[:3], lo, key[3], device, per, stage[key].train, first)
        out[("compile", key)] = first[0] if first else 0.0
        t_hi = t_lo if hi == lo else step_seconds(*key[:3], hi, key[3], device, per, stage[key].train)
        out[key] = (lo, t_lo, hi, t_hi)
        log(f"calibrated {key[1]} on {key[0]} (T_h {key[2]}): {t_lo * 1e3:.1f} ms at B={lo}"
            + (f", {t_hi * 1e3:.1f} ms at B={hi}" if hi != lo else ""))
    return out


def _median_seconds(step, max_s: float, device="cpu", first: list | None = None) -> float:
    """Median seconds of ``step()`` over the calls that fit in ``max_s`` of wall time (at least 2, at most 20),
    after one warm-up call. On the CPU the seconds are the calling thread's CPU time (torch runs on it with one
    thread): what a step costs a run that has a core to itself, whatever else loads the machine while the
    estimate measures (wall time read 5-11x high on a loaded machine); on a GPU, wall time."""
    clock = time.thread_time if torch.device(device).type == "cpu" else time.perf_counter
    t0 = time.process_time()    # (a compile runs in worker threads too)
    step()
    if first is not None:
        first.append(time.process_time() - t0)
    times, t_start = [], time.perf_counter()
    while len(times) < 2 or (time.perf_counter() - t_start < max_s and len(times) < 20):
        t0 = clock()
        step()
        times.append(clock() - t0)
    return float(np.median(times))


def stacked_step_seconds(members: list[tuple], B: int, device="cpu", max_s: float = 5.0,
                         first: list | None = None) -> float:
    """Measured seconds of one step of runs trained as one stack (:class:`sdp_cli.training.train_step.Stack`, the
    trainer's own step: per-member draws and losses, the stacked network, each member's clipping, AdamW and EMA)
    on synthetic batches of ``B``; ``members``: ``(task, method, T_h, action, train)`` per run (their own
    methods and Sobolev settings: a mixed SDP/DP stack pays the tangent pass for every member); as
    :func:`step_seconds` otherwise (the stack compiles itself where the config says so)."""
    from sdp_cli.training.train_step import Stack

    stack = Stack(_timed_runs(members, B, device))
    return _median_seconds(_step_of(stack), max_s, device, first)


def job_step_seconds(sts: list[TrainStage], cache: dict, max_s: float = 3.0, log=lambda s: None) -> float:
    """Measured seconds of one training step of a job of the runs ``sts`` (one :class:`TrainStage` each): a
    stack's (:func:`stacked_step_seconds`, batches padded to the largest, each member its own method), or one
    run's (:func:`step_seconds`); measured once per (members' :attr:`TrainStage.key`, B) in ``cache``."""
    s0 = sts[0]
    key = job_key(sts)
    R, B = len(sts), key[1]
    if key not in cache:
        first = [] if s0.train is not None and s0.train.compile else None
        cache[key] = (step_seconds(s0.task, s0.method, s0.T_h, B, s0.action, "cpu", max_s, s0.train, first) if R == 1
                      else stacked_step_seconds([(s.task, s.method, s.T_h, s.action, s.train) for s in sts], B,
                                                "cpu", max_s, first))
        cache[("compile", *key)] = first[0] if first else 0.0
        methods = "/".join(dict.fromkeys(s.method for s in sts))
        tasks = "/".join(dict.fromkeys(s.task for s in sts))
        log(f"calibrated a stack of {R} {methods} runs on {tasks} (T_h {s0.T_h}, B={B}): "
            f"{cache[key] * 1e3:.1f} ms a step")
    return cache[key]


def job_key(sts: list[TrainStage]) -> tuple:
    """What a job's step time depends on: its members' :attr:`TrainStage.key` and the batch it pads to."""
    return tuple(s.key for s in sts), max(s.B for s in sts)


def _interp(cal: tuple, B: int) -> float:
    """A step's seconds at batch ``B`` from two measured ones, linear between them; below the smaller batch
    the smaller's (a small step is per-op overhead: extrapolating the line went negative, rollouts of -0.001 h)."""
    lo, t_lo, hi, t_hi = cal
    return t_lo if hi == lo or B <= lo else t_lo + (t_hi - t_lo) * (B - lo) / (hi - lo)


def estimate(name: str, workers: int = 2, budget_s: float = 60.0, log=lambda s: None,
             root: Path = Path("."), stack: int | None = None, only: list[str] | None = None) -> tuple[pd.DataFrame, dict]:
    """Per-run estimate of experiment ``name`` and the totals (see the module docstring). Runs that
    ``sdp pipeline --run`` trains as one stack (``stack`` runs at most, :func:`sdp_cli.experiments.runner.pack`) share
    the measured time of a stacked step (:func:`stacked_step_seconds`) instead of one step each. ``only``: the run
    names to estimate (``--only``, as ``--run`` takes it; default all), stacked among themselves."""
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.experiments.pipeline import check_only, loop_configs

    if workers <= 0:
        raise SdpError(f"workers must be > 0, got {workers}")
    if stack is not None and stack <= 0:
        raise SdpError(f"--stack must be >= 1, got {stack}")
    runs = loop_configs(name, load_experiment(name, root))
    if only:
        check_only(name, runs, only)
        runs = {k: v for k, v in runs.items() if k in set(only)}
    train = training_stages(runs)
    if not train:
        raise SdpError(f"experiment {name!r} has no training stage")
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(1)    # every measurement on one thread, as the runs train (the stacks' too: on the
    try:                        # process's default threads, beside two runs, a stack of 3 measured 6.7 s a step, not 0.1 s)
        return _estimate(runs, train, devices, workers, budget_s, log, stack)
    finally:
        torch.set_num_threads(prev_threads)


def _estimate(runs: dict, train: list[TrainStage], devices: list[str], workers: int, budget_s: float, log,
              stack: int | None) -> tuple[pd.DataFrame, dict]:
    cals = {d: calibrate(train, d, budget_s / len(devices), log) for d in devices}
    rows: dict[str, dict] = {}
    for st in train:
        r = rows.setdefault(st.run, {"run": st.run, "task": st.task, "method": st.method, "iterations": 0,
                                     "steps": 0, "samples": 0, **{f"train_{d}_s": 0.0 for d in devices},
                                     "to_s": 0.0, "rollout_s": 0.0})
        r["iterations"] += 1
        r["steps"] += st.steps
        r["samples"] += st.epochs * st.E
        for d in devices:
            r[f"train_{d}_s"] += st.steps * _interp(cals[d][st.key], st.B) + cals[d][("compile", st.key)]
    from sdp_cli.experiments.runner import pack

    stacked: dict = {}
    for job in (j for j in pack(runs, DEFAULT_STACK if stack is None else stack) if len(j) > 1):
        total = 0.0
        for k in range(runs[job[0]].n_algo):   # each iteration: one stacked training of the members' data
            sts = [next(s for s in train if s.run == run and s.iteration == k) for run in job]
            seconds = job_step_seconds(sts, stacked, log=log)
            longest = max(s.steps for s in sts)   # the stack runs as long as its longest member
            total += longest * seconds + stacked[("compile", *job_key(sts))]
        for run in job:   # each member bears an equal share
            rows[run]["stack"] = len(job)
            rows[run]["train_cpu_s"] = total / len(job)   # (GPU columns: solo steps)
    for run, cfg in runs.items():
        r, task = rows[run], get_task(cfg.task)
        ms, ss = to_reference(cfg.task, cfg.to)
        st = next(s for s in train if s.run == run)
        # collection: the naive guess at iteration 0, then policy guess and naive guess (ArgminCost)
        r["to_s"] += sum(cfg.n_traj_at(k) * ms * (1 if k == 0 else 2) for k in range(cfg.n_algo))
        ro = cfg.rollout
        fwd = _interp(cals["cpu"][st.key], min(ro.n_test, st.B)) / 3
        for k in range(cfg.n_algo):
            t_as = list(ro.eval_t_a or (ro.t_a,))
            if k == cfg.n_algo - 1:
                t_as += [t for t in ro.eval_t_a_last if t not in t_as]
            for t_a in t_as * (1 + len(cfg.save_at)):   # the final checkpoint and the save_at ones
                if ro.eval_refine:
                    r["to_s"] += 2 * ro.n_test * ms + (2 * ro.n_test * ss if ro.single_shooting else 0.0)
                t_a = t_a or max(1, cfg.train.policy.max_t_a)
                family = cfg.train.policy_class   # network calls per plan: the sampler's (K or k_rollout) or 1
                k = ro.k_rollout or family.sampler_steps(cfg.train) or 1
                calls = (math.ceil(task.T / t_a) * k) if family.chunked else task.T
                r["rollout_s"] += calls * fwd
    df = pd.DataFrame(list(rows.values()))
    if "stack" in df:
        df["stack"] = df["stack"].fillna(1).astype(int)
    for d in devices:
        df[f"total_{d}_s"] = df[f"train_{d}_s"] + df["to_s"] + df["rollout_s"]
    totals = {}
    for d in devices:
        col = df[f"total_{d}_s"]
        totals[d] = {"sequential_s": float(col.sum()),
                     "workers": workers, "parallel_s": float(max(col.sum() / workers, col.max()))}
    return df, totals


def format_estimate(name: str, df: pd.DataFrame, totals: dict) -> str:
    """The table ``sdp pipeline --estimate`` prints: hours per run and the totals."""
    show = df.copy()
    for c in [c for c in show.columns if c.endswith("_s")]:
        show[c.replace("_s", "_h")] = show.pop(c) / 3600
    lines = [f"estimate for {name!r}: {len(df)} runs, {int(df.steps.sum())} training steps, "
             f"{int(df.samples.sum())} samples (training time measured here; TO times are references)",
             show.to_string(index=False, float_format=lambda v: f"{v:.3f}")]
    for d, t in totals.items():
        lines.append(f"total on {d}: {t['sequential_s'] / 3600:.2f} h in one process; "
                     f"{t['parallel_s'] / 3600:.2f} h with {t['workers']} parallel workers")
    return "\n".join(lines)

"""The runs of an experiment in parallel: ``sdp pipeline NAME --run``.

Every run of ``pipelines/NAME.yaml`` (one per group x method x seed x n_traj) is one
``sdp loop`` (:func:`sdp_cli.algorithm.loop.run_loop`) in ``OUT/<task>-<method>-n<n_traj>-s<seed>/``:
collect, train, evaluate, for each iteration, with the collection seeds of the DVC stages
(``1000 * seed + k``) and the ``save_at`` epochs evaluated from the same training. The runs
are independent, so they are jobs of an executor (:mod:`sdp_cli.execution.executor`):

- ``local``: a pool of ``workers`` processes, one torch thread each (inside a run the solves
  run serially: the parallelism is across runs);
- ``dask``: a ``LocalCluster`` of ``workers`` processes, or the workers of a running
  scheduler (``--scheduler tcp://HOST:PORT``); ``OUT`` must then be on a file system that
  every worker sees (as on a cluster's shared home or scratch).

Resume and failures: a run writes every stage atomically and training checkpoints every
minute, so a run started again continues where it stopped (``sdp loop`` resume). A run whose
worker died (killed, out of memory, node lost) is submitted again and resumes; a run that
raised is reported and the others go on; the command fails at the end if any run failed.
Running it again after an interruption redoes only what is missing. Results equal those of
running the runs one after another (same seeds, one thread each; tested).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import multiprocessing as mp
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

import pandas as pd

from sdp_cli.data.artifacts import ensure_dir
from sdp_cli.errors import SdpError
from sdp_cli.execution.executor import check_executor_options, error_status, make_executor
from sdp_cli.training.train_stack import DEFAULT_STACK, stack_key, stackable, train_stack

#: environment defaults of ``sdp pipeline --run`` (so that the DVC stage's command, and with it
#: its hash, is the same on a laptop and on a cluster)
ENV_EXECUTOR, ENV_WORKERS, ENV_SCHEDULER = "SDP_EXECUTOR", "SDP_WORKERS", "SDP_SCHEDULER"


def _leave_if_pool_worker() -> None:
    """A pool worker stopped by Ctrl-C/SIGTERM has written its checkpoints at a step boundary: it exits (130)
    without a traceback; elsewhere the ``KeyboardInterrupt`` goes on."""
    if mp.parent_process() is not None:
        os._exit(130)


def run_job(config: dict, out: str, device: str = "auto") -> list[dict]:
    """One run, in a worker process: ``sdp loop`` with one torch thread; its summary rows."""
    import torch

    from sdp_cli.algorithm.loop import LoopConfig, run_loop
    from sdp_cli.training.train import resolve_device

    torch.set_num_threads(1)
    name = Path(out).name

    def log(line: str) -> None:   # one line per stage of each run (what `dvc repro` shows while it trains)
        print(f"{name}: {line.strip()}", file=sys.stderr, flush=True)

    cfg = LoopConfig.from_dict(config, device=str(resolve_device(device)))
    try:
        return run_loop(cfg, out, log=log).to_dict("records")
    except KeyboardInterrupt:
        _leave_if_pool_worker()
        raise


def run_stack_job(configs: list[dict], outs: list[str], device: str = "auto") -> dict[str, list[dict]]:
    """Compatible runs (:func:`pack`) in lockstep, in a worker process: at each iteration of Algorithm 1, each run's
    collection (warm-started by its own previous policy) and buffer, then their training as one stack
    (:func:`sdp_cli.training.train_stack.train_stack`, each warm-started from its own previous policy); then each run's
    evaluations (``sdp loop``, which finds the data and the finished policies of every iteration);
    ``{run: summary rows}``. Every run keeps its own datasets, seeds, checkpoints and numbers, and a killed job
    resumes where it stopped (the datasets and checkpoints that exist are kept)."""
    import torch

    from sdp_cli.algorithm.loop import LoopConfig, begin_loop, iteration_data, run_loop, train_done
    from sdp_cli.training.train import resolve_device

    torch.set_num_threads(1)
    cfgs = [LoopConfig.from_dict(c, device=str(resolve_device(device))) for c in configs]
    outs = [begin_loop(cfg, out) for cfg, out in zip(cfgs, outs)]
    names = [o.name for o in outs]

    def logger(name):
        return lambda line: print(f"{name}: {line.strip()}", file=sys.stderr, flush=True)

    failed: dict[str, str] = {}   # {run: why}: a member that fails leaves the stack, the others go on
    live = lambda: [i for i, n in enumerate(names) if n not in failed]   # noqa: E731
    try:
        for k in range(cfgs[0].n_algo):
            prev = [o / f"it{k - 1}" / "policy" if k else None for o in outs]
            datas = {}
            for i in live():
                try:
                    datas[i] = iteration_data(cfgs[i], outs[i], k, prev[i], logger(names[i]))
                except Exception as e:   # noqa: BLE001 - one member's failed collection is that member's
                    failed[names[i]] = error_status(e)
            todo = [i for i in live() if not train_done(outs[i] / f"it{k}" / "policy")]
            if todo:
                logger(" + ".join(names[i] for i in todo))(f"[it{k}] train {len(todo)} runs as one stack"
                                                           + (" (init from previous)" if k else ""))
                diverged: dict = {}
                train_stack([datas[i] for i in todo], [outs[i] / f"it{k}" / "policy" for i in todo],
                            [cfgs[i].train for i in todo], device=cfgs[0].device, log=lambda s: None,
                            inits=[prev[i] / "checkpoint.pt" if k else None for i in todo], failed=diverged)
                for i in todo:
                    if outs[i] / f"it{k}" / "policy" in diverged:
                        failed[names[i]] = "error: " + diverged[outs[i] / f"it{k}" / "policy"]
                        logger(names[i])(f"[it{k}] FAILED, left the stack: {failed[names[i]]}")
        out = {}
        for i in range(len(names)):
            if names[i] in failed:
                out[names[i]] = failed[names[i]]
                continue
            try:
                out[names[i]] = run_loop(cfgs[i], outs[i], log=logger(names[i])).to_dict("records")
            except Exception as e:   # noqa: BLE001
                out[names[i]] = error_status(e)
        return out
    except KeyboardInterrupt:
        _leave_if_pool_worker()
        raise


def run_jobs(configs: list[dict], outs: list[str], device: str = "auto", job: Callable = run_job) -> dict[str, list[dict]]:
    """One job of the executor: one run (``job``, :func:`run_job`) or a stack of compatible runs
    (:func:`run_stack_job`); ``{run: summary rows}``."""
    if len(configs) == 1:
        return {Path(outs[0]).name: job(configs[0], outs[0], device)}
    return run_stack_job(configs, outs, device)


def pack(runs: dict, stack: int) -> list[list[str]]:
    """The jobs of an experiment's runs (``{name: LoopConfig}``, in the experiment's order): runs of a stackable,
    compatible training config (:func:`sdp_cli.training.train_stack.stack_key`: one network shape, whatever the
    task variant, seed or T_a) with the same tangent pass (the Sobolev term or none), of one number of
    iterations, buffer rule and dataset sizes at every iteration share stacks of up to ``stack`` runs (a group larger than ``stack`` is
    split into near-equal stacks, in the experiment's order), trained in lockstep (:func:`run_stack_job`: each
    iteration's collections, then one stacked training); every other run is a job of its own. One size per stack:
    a stack pads its members' batches to its largest, so filling stacks across sizes (until 2026-11-27) spent
    1.25-1.35x the time on padding rows (``bench/stack_packing.py``). Stacks first, the larger datasets first
    within a training config (the longest jobs start first), then the runs alone; the same experiment gives the
    same jobs on every machine. SDP and DP could share a stack (:func:`~sdp_cli.training.train_stack.train_stack`
    trains them together), but a DP member then pays SDP's tangent pass: fig3's stacks of 4-6 mixed runs cost
    1.0-1.3x the CPU of the same runs in one stack per method (``sdp pipeline fig3 --estimate --stack 8``,
    docs/training.md), so the tangent pass is part of the key."""
    groups: dict = {}
    alone: list[list[str]] = []
    for name, cfg in runs.items():
        if stack > 1 and stackable(cfg.train):
            sizes = tuple(cfg.n_traj_at(k) for k in range(cfg.n_algo))
            key = (stack_key(cfg.task, cfg.train), cfg.train.uses_sobolev, cfg.n_algo, cfg.reset_buffer)
            groups.setdefault(key, {}).setdefault(sizes, []).append(name)
        else:
            alone.append([name])
    jobs = []
    for sizes in groups.values():
        for n_traj in sorted(sizes, key=lambda s: s[::-1], reverse=True):
            jobs += split_even(sizes[n_traj], stack)
    return jobs + alone


def split_even(names: list[str], most: int) -> list[list[str]]:
    """``names`` in order, cut into ``ceil(len / most)`` consecutive parts whose lengths differ by at most one
    (10 runs at most 8: 5 + 5, not 8 + 2)."""
    k = -(-len(names) // most)
    q, r = divmod(len(names), k)
    out, i = [], 0
    for j in range(k):
        n = q + (j < r)
        out.append(names[i:i + n])
        i += n
    return out


def executor_options(executor: str | None, workers: int | None, scheduler: str | None) -> tuple:
    """Options given on the command line, else from ``SDP_EXECUTOR``/``SDP_WORKERS``/``SDP_SCHEDULER``."""
    executor = executor or os.environ.get(ENV_EXECUTOR) or None
    scheduler = scheduler or os.environ.get(ENV_SCHEDULER) or None
    if workers is None and os.environ.get(ENV_WORKERS):
        try:
            workers = int(os.environ[ENV_WORKERS])
        except ValueError:
            raise SdpError(f"{ENV_WORKERS} must be an integer, got {os.environ[ENV_WORKERS]!r}") from None
    return executor, workers, scheduler


def run_group(name: str, out: str | os.PathLike, executor: str | None = None, workers: int | None = None,
              scheduler: str | None = None, device: str = "auto", only: list[str] | None = None,
              restart_changed: bool = False, log: Callable[[str], None] = print, job: Callable = run_job,
              root: Path = Path("."), stack: int | None = None) -> pd.DataFrame:
    """Run (or resume) every run of experiment ``name`` under ``out``; their summaries, one table.

    ``only``: run names to run (default all). ``restart_changed``: a run folder holding a run with
    other settings (the experiment file changed) or of another results version
    (:data:`sdp_cli.RESULTS_VERSION`) is moved aside (:func:`supersede`, never deleted) and the run
    starts over; otherwise other settings are refused before anything runs and another results version
    is resumed. ``job``: the per-run function (tests substitute one that kills its worker once). ``stack``: runs
    per stack of compatible runs (:func:`pack`; default :data:`sdp_cli.training.train_stack.DEFAULT_STACK`,
    1: every run alone)."""
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.experiments.pipeline import check_only, loop_configs

    executor, workers, scheduler = executor_options(executor, workers, scheduler)
    check_executor_options(executor, workers, scheduler)
    runs = loop_configs(name, load_experiment(name, root))
    check_only(name, runs, only)   # every refusal that needs no run folder comes before the lock (which would stay behind)
    if stack is not None and stack <= 0:
        raise SdpError(f"--stack must be >= 1, got {stack}")
    with runner_lock(Path(out)):
        return _run_group(name, runs, Path(out), executor, workers, scheduler, device, only, restart_changed, log, job,
                          stack)


def lock_path(out: Path) -> Path:
    """The lock of the runs in ``out``: beside the folder (``runs/.small.lock``), outside the DVC output."""
    out = Path(out).resolve()
    return out.parent / f".{out.name}.lock"


@contextlib.contextmanager
def runner_lock(out: Path):
    """One runner per run folder: a second ``sdp pipeline --run`` (or ``dvc repro``) on the same folder
    refuses with one line naming the owner's pid instead of training the same runs twice at once. An
    ``flock``: released by the kernel when its holders die (no stale lock after a ``kill -9``); the pool
    workers inherit it, so it is held while any of them still writes."""
    path = lock_path(out)

    ensure_dir(path.parent, "runs' parent folder")
    while True:
        created = not path.exists()
        f = open(path, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            owner = f.read().strip() or "unknown"
            f.close()
            raise SdpError(f"{out} is being run by another `sdp pipeline --run` (pid {owner}); wait for it to "
                           f"finish or stop it (its lock: {path})") from None
        try:   # locked; but a runner that refused may have removed this file since we opened it: lock the new one
            same = os.stat(path).st_ino == os.fstat(f.fileno()).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        f.close()
    try:
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        yield
    except SdpError:
        if created:   # refused (settings of a run folder, ...): leave no lock file that this call made
            path.unlink(missing_ok=True)
        raise
    finally:
        fcntl.flock(f, fcntl.LOCK_UN)
        f.close()


def _run_group(name, runs, out, executor, workers, scheduler, device, only, restart_changed, log, job, stack=None):
    from sdp_cli.algorithm.loop import check_resume
    from sdp_cli.progress import count_progress

    if only:   # names checked by run_group
        runs = {k: v for k, v in runs.items() if k in only}
    out = Path(out)
    for key, cfg in runs.items():   # a folder holding other settings: refused (or restarted) before any work
        try:
            check_resume(cfg, out / key, same_results=restart_changed)
        except SdpError as e:
            if not restart_changed:
                raise
            moved = supersede(out / key)
            log(f"  {key}: {str(e).split(': ', 1)[-1].removesuffix('; use another --out')}; moved the old run "
                f"to {moved} and starting it over")


    jobs = pack(runs, DEFAULT_STACK if stack is None else stack)
    argsets = [([runs[k].to_dict() for k in job_keys], [str(out / k) for k in job_keys], device) for job_keys in jobs]
    tables, failed = [], []
    n_runs = len(runs)
    with make_executor(executor, workers, scheduler) as ex:
        stacked = sum(len(j) for j in jobs if len(j) > 1)
        log(f"{n_runs} runs of {name!r} on {ex.describe()}" +
            (f" ({stacked} of them in {sum(1 for j in jobs if len(j) > 1)} stacks)" if stacked else ""))
        with count_progress(f"{name} (runs)", n_runs, True) as on_done:
            done = 0
            for i, res in ex.imap_unordered(functools.partial(run_jobs, job=job), argsets):
                names = ", ".join(jobs[i])
                if res.ok:   # a stack's member that failed alone has its status in place of its rows
                    bad = {run: why for run, why in res.value.items() if isinstance(why, str)}
                    for run, rows in res.value.items():
                        if run not in bad:
                            tables.append(pd.DataFrame(rows).assign(run=run))
                    failed += [f"{run} ({why})" for run, why in bad.items()]
                    for run, why in bad.items():
                        log(f"  {run}: FAILED: {why}")
                    if len(bad) < len(jobs[i]):
                        log(f"  {', '.join(r for r in jobs[i] if r not in bad)}: done")
                else:
                    failed += [f"{k} ({error_status(res.error)})" for k in jobs[i]]
                    log(f"  {names}: FAILED: {error_status(res.error)}")
                done += len(jobs[i])
                on_done(done, n_runs)
    keys = list(runs)
    if failed:
        raise SdpError(f"{len(failed)} of {len(keys)} runs failed: {'; '.join(failed)}; the others are kept, "
                       "re-run to retry the failed ones")
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()


def superseded_dir(out: Path) -> Path:
    """Where :func:`supersede` moves the runs of ``out`` (``runs/NAME`` -> ``runs/superseded/NAME``):
    beside the experiment's folder, outside the DVC output, so DVC's cache does not grow with them."""
    out = Path(out).resolve()
    return out.parent / "superseded" / out.name


def supersede(run_dir: Path) -> Path:
    """Move a run folder aside (never delete it): to ``superseded/<experiment>/<run>-<UTC time>``."""
    run_dir = Path(run_dir)
    dest_root = superseded_dir(run_dir.parent)
    dest_root.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    dest, n = dest_root / f"{run_dir.name}-{stamp}", 1
    while dest.exists():
        n += 1
        dest = dest_root / f"{run_dir.name}-{stamp}-{n}"

    shutil.move(str(run_dir), str(dest))   # a rename on one file system
    return dest


def run_status(name: str, out: str | os.PathLike, root: Path = Path(".")) -> pd.DataFrame:
    """Where each run of experiment ``name`` under ``out`` stands, from its folder (reads only):
    ``run``, ``iterations`` (evaluated iterations / n_algo), ``state`` (done: its summary is written;
    in progress: a folder with work in it; not started; other settings: the folder holds a run made
    with other settings, which ``--run`` refuses and ``--restart-changed`` starts over)."""
    from sdp_cli.algorithm.evaluate import manifest_path
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.algorithm.loop import check_resume
    from sdp_cli.experiments.pipeline import loop_configs

    rows = []
    for key, cfg in loop_configs(name, load_experiment(name, root)).items():
        d = Path(out) / key
        done = sum(1 for k in range(cfg.n_algo) if manifest_path(d / f"it{k}" / "eval" / "eval.csv").is_file())
        try:
            check_resume(cfg, d)
            same = True
        except SdpError:
            same = False
        state = ("other settings" if not same else "done" if (d / "summary.csv").is_file() and done == cfg.n_algo
                 else "in progress" if d.is_dir() and any(d.iterdir()) else "not started")
        rows.append({"run": key, "iterations": f"{done}/{cfg.n_algo}", "state": state})
    return pd.DataFrame(rows)


def status_text(name: str, out: str | os.PathLike, root: Path = Path(".")) -> str:
    """``sdp pipeline NAME --status``: :func:`run_status`'s table and a line of counts."""
    table = run_status(name, out, root)
    counts = table.state.value_counts()
    return table.to_string(index=False) + "\n" + ", ".join(
        f"{counts[k]} {k}" for k in ("done", "in progress", "not started", "other settings") if k in counts)


def summary_text(summary: pd.DataFrame) -> str:
    """``sdp pipeline NAME --run``'s closing table: each run's evaluations, the main columns."""
    cols = [c for c in ("run", "iteration", "epochs", "t_a", "policy_cost_mean", "success_rate",
                        "refined_cost_mean", "to_alone_cost_mean") if c in summary]
    return summary[cols].to_string(index=False) if len(summary) else "no runs"

"""``sdp collect``: solve OCPs from the naive guess and keep the converged ones.

Determinism: ``xi_i`` is a function of ``(seed, i)`` only (:func:`sample_xi`), every
index is solved independently, and the kept set is the first ``n_traj`` converged
indices in index order, whatever the number of workers or the completion order.

Resumability: every finished solve (converged or not) is written atomically to
``<out>.partial/<i>.npz`` by the main process before it is counted, next to a
``manifest.json`` holding the run's configuration. Re-running the same command after a
crash (even ``kill -9``) reuses those files and solves only what is missing. The final
artifact is written atomically, then the partial folder is removed. The wall time it records is summed over
the runs that built it: each save also records the run's elapsed time so far (``elapsed.json``), which a
resumed run starts from (time after the last save of a crashed run, whose solve is redone, is not counted).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
import hashlib
from typing import Callable, Iterator

import numpy as np

from sdp_cli.families import DEFAULT_TO
from sdp_cli.data.artifacts import (artifact_writes, atomic_write_bytes, check_writable, load_npz, portable_path, save_npz,
                                    split_timing)
from sdp_cli.errors import SdpError
from sdp_cli.rules import check_fields, rule
from sdp_cli.algorithm.solve_jobs import (RESULT_KEYS, failed_result, instance_arrays, job_chunks, job_size,  # noqa: F401
                                 refine_indices, sample_xi, solve_index, solve_indices, warm_solver)
from sdp_cli.tasks import Task, get_task
from sdp_cli.seeds import check_seed
from sdp_cli.trajopt import check_to
from sdp_cli.tasks.conversion import check_conversion
from sdp_cli.execution.executor import Executor, check_executor_options, error_status, make_executor


@dataclass(frozen=True)
class CollectConfig:
    """Everything that determines a collection's content."""

    task: str
    n_traj: int = field(metadata=rule(ge=1))
    seed: int = 0
    max_iter: int = field(default=1000, metadata=rule(ge=1))
    max_attempts: int | None = field(default=None, metadata=rule(ge=1))  # default: 20 * n_traj
    task_options: dict = field(default_factory=dict)
    #: Algorithm 1 lines 3-8: warm-start TO with this policy's rollout, keep ArgminCost
    policy: str | None = None
    policy_fingerprint: str | None = None
    t_a: int | None = field(default=None, metadata=rule(ge=1))
    k_rollout: int | None = field(default=None, metadata=rule(ge=1))
    #: with a policy: how its predicted chunks become controls (sdp_cli.tasks.conversion; None: the task's)
    conversion: str | None = None
    #: the TO family (sdp_cli.families): "ms" (DEFAULT_TO: fatrop) or "ddp" (box-FDDP, the paper's)
    to: str = DEFAULT_TO

    def __post_init__(self):
        check_seed(self.seed)
        check_to(self.to)
        check_fields(self)

        check_conversion(self.conversion)
        if self.policy is None and (self.t_a is not None or self.k_rollout is not None or self.conversion):
            raise SdpError("--t-a, --k-rollout and --conversion set the policy's rollouts: they need --policy")
        if self.max_attempts is not None and self.max_attempts < self.n_traj:
            raise SdpError(f"max_attempts ({self.max_attempts}) must be >= n_traj ({self.n_traj})")

    @property
    def attempts_cap(self) -> int:
        return self.max_attempts if self.max_attempts is not None else 20 * self.n_traj

    def identity(self) -> dict:
        """The part of the config that partial results must agree on (not the caps)."""
        ident = {"task": self.task, "seed": self.seed, "max_iter": self.max_iter,
                 "task_options": dict(sorted(self.task_options.items()))}
        if self.to != DEFAULT_TO:   # (partial results of collections made before --to existed stay valid)
            ident["to"] = self.to
        if self.policy is not None:
            ident.update(policy=self.policy_fingerprint, t_a=self.t_a, k_rollout=self.k_rollout)
            if self.conversion is not None:   # (partial results made before the setting existed stay valid)
                ident["conversion"] = self.conversion
        return ident


class _Jobs:
    """Turns sample indices into solver jobs ``(fn, args)``: naive guess, or policy guess."""

    def __init__(self, config: CollectConfig, task: Task):
        self.config, self.task = config, task
        self.policy = None
        if config.policy is not None:
            from sdp_cli.policy import load_policy
            from sdp_cli.algorithm.rollout import RolloutConfig

            self.policy = load_policy(config.policy, device="cpu")
            if self.policy.task_name != config.task:
                raise SdpError(f"policy {config.policy} was trained on task {self.policy.task_name!r}, "
                               f"not {config.task!r}")
            self.rcfg = RolloutConfig(n=1, seed=config.seed, t_a=config.t_a, k_rollout=config.k_rollout,
                                      conversion=config.conversion).validate(self.policy)

    def make(self, indices: list[int]) -> list[tuple[Callable, tuple, list[int]]]:
        """Jobs ``(fn, args, indices)``: one per index, or (``to="ddp"``) one per batch of up to
        :data:`~sdp_cli.algorithm.solve_jobs.DDP_BATCH` indices solved together; every job returns a list of results."""
        c = self.config
        chunks = job_chunks(indices, c.to)
        if self.policy is None:
            return [(solve_indices, (c.task, c.task_options, c.seed, ch, c.max_iter, c.to), ch) for ch in chunks]
        import torch

        from sdp_cli.algorithm.rollout import instance_generators, rollout_policy

        xis = np.stack([sample_xi(self.task, c.seed, i) for i in indices])
        with torch.no_grad():
            traj = rollout_policy(self.policy, xis, self.rcfg,
                                  generators=instance_generators(c.seed, indices))
        pos = {i: k for k, i in enumerate(indices)}
        return [(refine_indices, (c.task, c.task_options, ch, [xis[pos[i]] for i in ch],
                                  [traj["X"][pos[i]] for i in ch], [traj["U"][pos[i]] for i in ch], c.max_iter, c.to),
                 ch) for ch in chunks]


def policy_fingerprint(path: str | os.PathLike) -> str:
    """Content hash of a checkpoint (a run folder means its ``checkpoint.pt``)."""
    p = Path(path)
    if p.is_dir():
        p = p / "checkpoint.pt"
    if not p.is_file():
        raise SdpError(f"policy checkpoint not found: {path}")
    return hashlib.sha256(p.read_bytes()).hexdigest()[:16]


# ----------------------------------------------------------------- partial store
class PartialStore:
    """Per-index results of an unfinished collection in ``<out>.partial/``."""

    def __init__(self, out: Path, config: CollectConfig):
        self.dir = out.with_name(out.name + ".partial")
        self.config = config
        manifest = self.dir / "manifest.json"
        if self.dir.exists():
            try:
                old = json.loads(manifest.read_text())
            except (OSError, json.JSONDecodeError):
                raise SdpError(f"corrupt partial results in {self.dir} (bad manifest.json); "
                               "delete the folder to start over") from None
            if old != config.identity():
                raise SdpError(f"partial results in {self.dir} come from a different configuration "
                               f"({old}); delete the folder or choose another --out")
        else:   # created with the first result, so that a run rejected before any solve leaves nothing
            check_writable(out)

    def _create(self) -> None:
        ident = json.dumps(self.config.identity()).encode()
        atomic_write_bytes(self.dir / "manifest.json", lambda f: f.write(ident))   # creates the folder

    def path(self, index: int) -> Path:
        return self.dir / f"{index:06d}.npz"

    def save(self, result: dict, elapsed: float) -> None:
        """Persist one finished solve, and ``elapsed`` (s), the collection's wall time up to it."""
        data = json.dumps({"wall_time": float(elapsed)}).encode()
        with artifact_writes():   # one solve (with the folder's manifest the first time): all of it or nothing
            if not (self.dir / "manifest.json").is_file():
                self._create()
            save_npz(self.path(int(result["index"])), result, kind="solve", config=self.config.identity())
            atomic_write_bytes(self.dir / "elapsed.json", lambda f: f.write(data))

    def elapsed(self) -> float:
        """Wall time (s) the earlier runs spent up to their last saved solve (0: a fresh collection)."""
        try:
            return float(json.loads((self.dir / "elapsed.json").read_text())["wall_time"])
        except FileNotFoundError:
            return 0.0
        except (OSError, ValueError, KeyError, TypeError):
            raise SdpError(f"corrupt partial results in {self.dir} (bad elapsed.json); delete that file "
                           "(only the recorded wall time is lost)") from None

    def load_all(self) -> dict[int, dict]:
        done = {}
        if not self.dir.is_dir():
            return done
        for p in sorted(self.dir.glob("[0-9]*.npz")):
            arrays, meta = load_npz(p, kind="solve")
            if meta.get("config") != self.config.identity() or "index" not in arrays:
                raise SdpError(f"corrupt partial file {p} (foreign configuration); delete it")
            missing = [k for k in RESULT_KEYS if k not in arrays]
            if missing:
                raise SdpError(f"corrupt partial file {p} (missing {', '.join(missing)}); delete it")
            done[int(arrays["index"])] = arrays
        return done

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


# --------------------------------------------------------------- index schedule
def kept_indices(done: dict[int, dict], n_traj: int) -> list[int] | None:
    """First ``n_traj`` converged indices if every smaller index is finished, else None."""
    kept = []
    i = 0
    while i in done:
        if bool(done[i]["converged"]):
            kept.append(i)
            if len(kept) == n_traj:
                return kept
        i += 1
    return None


def _next_indices(done: dict, inflight: set, n_traj: int, cap: int) -> Iterator[int]:
    """Indices to submit next, lowest first, never more than needed optimistically."""
    top = max(done, default=-1)
    for i in range(min(top, cap)):  # holes left by a crash always come first
        if i not in done and i not in inflight:
            yield i
    n_conv = sum(bool(r["converged"]) for r in done.values())
    need = n_traj - n_conv - len(inflight)
    i = top + 1
    while need > 0 and i < cap:
        if i not in inflight:
            yield i
            need -= 1
        i += 1


@dataclass
class CollectStats:
    attempts: int = 0
    kept: int = 0
    rejected: int = 0
    mean_solve_time: float = 0.0
    convergence_rate: float = 0.0
    wall_time: float = 0.0


def _run(ex, jobs: _Jobs, task: Task, config: CollectConfig, done: dict, update: Callable) -> None:
    """Keep ``ex`` busy with the next indices until the kept set is decided; persist each result.

    Results are handled as they finish; a job that raised becomes a failed attempt, a job
    lost with its worker is not counted and gets submitted again by the next round.
    """
    cap = config.attempts_cap
    inflight: dict = {}     # future -> the indices it solves
    size = job_size(config.to)
    try:
        while kept_indices(done, config.n_traj) is None:
            room = (ex.max_inflight or max(1, config.n_traj)) - len(inflight)
            busy = {i for idxs in inflight.values() for i in idxs}
            todo = list(itertools.islice(_next_indices(done, busy, config.n_traj, cap), max(room, 0) * size))
            for fn, a, idxs in jobs.make(todo) if todo else []:
                inflight[ex.submit(fn, *a)] = idxs
            if not inflight:
                break
            for fut in sorted(ex.wait_any(list(inflight)), key=lambda f: inflight[f][0]):
                idxs = inflight.pop(fut)
                out = ex.outcome(fut)
                if out.lost:
                    continue
                if out.ok:
                    for value in out.value:
                        update(value)
                else:
                    for i in idxs:
                        update(failed_result(task, i, sample_xi(task, config.seed, i), error_status(out.error)))
    finally:
        ex.cancel(list(inflight))


def collect(config: CollectConfig, out: str | os.PathLike, workers: int | None = None,
            progress: Callable[[CollectStats], None] | None = None, executor: "str | Executor" = "local",
            scheduler: str | None = None) -> tuple[Path, CollectStats]:
    """Run a collection (resuming any partial results) and write the dataset artifact.

    ``executor``: ``"local"`` (process pool of ``workers``, default all cores), ``"dask"``
    (a LocalCluster of ``workers`` processes, or the cluster of ``scheduler``), or an open
    :class:`~sdp_cli.execution.executor.Executor` (used as is, not closed). The result does not
    depend on it.
    """
    out = Path(out)
    if out.exists() and out.is_dir():
        raise SdpError(f"--out {out} is a directory; give a file path such as {out}/dataset.npz")
    check_writable(out)   # a device, fifo or socket there is refused before any work
    task = get_task(config.task, **config.task_options)  # validates the name early

    check_to(config.to)
    if not isinstance(executor, Executor):
        check_executor_options(executor, workers, scheduler)  # bad options fail before any work
    jobs = _Jobs(config, task)   # loads and checks the policy before anything is written
    store = PartialStore(out, config)
    done = store.load_all()
    t_start = time.perf_counter() - store.elapsed()     # a resumed collection's wall time goes on from the earlier runs'
    stats = CollectStats()

    def update(result: dict | None = None) -> None:
        if result is not None:
            store.save(result, time.perf_counter() - t_start)
            done[int(result["index"])] = result
        conv = [r for r in done.values() if bool(r["converged"])]
        stats.attempts = len(done)
        stats.kept = min(len(conv), config.n_traj)
        stats.rejected = len(done) - len(conv)
        stats.mean_solve_time = float(np.mean([float(r["solve_time"]) for r in done.values()])) if done else 0.0
        stats.convergence_rate = len(conv) / len(done) if done else 0.0
        if progress:
            progress(stats)

    update()
    cap = config.attempts_cap
    described = {"kind": "none (resumed complete)"}
    if kept_indices(done, config.n_traj) is None:
        own = not isinstance(executor, Executor)
        ex = make_executor(executor, workers, scheduler) if own else executor
        try:
            described = ex.describe()
            # the casadi problem is built once per worker process (inherited by forked pool workers)
            ex.warm(warm_solver, config.task, config.task_options, config.max_iter, config.to)
            _run(ex, jobs, task, config, done, update)
        finally:
            if own:
                ex.close()
    kept = kept_indices(done, config.n_traj)
    stats.wall_time = time.perf_counter() - t_start
    if kept is None:
        n_conv = sum(bool(r["converged"]) for r in done.values())
        errors = [str(r["status"]) for r in done.values() if str(r.get("status", "")).startswith("error:")]
        why = f"; {len(errors)} raised an error, e.g. {errors[0]}" if errors else ""
        raise SdpError(f"only {n_conv} of {config.n_traj} solves converged after {len(done)} attempts "
                       f"(cap {cap}){why}; raise --max-attempts or --max-iter (finished solves are kept "
                       f"in {store.dir})")
    arrays = {k: np.stack([np.asarray(done[i][k]) for i in kept]) for k in RESULT_KEYS + ("xi", "index")}
    arrays["converged"] = arrays["converged"].astype(bool)
    if config.policy:   # every index tried, kept or not: the schema of `sdp refine` (solve_jobs.instance_arrays)
        tried = sorted(done)
        arrays.update(instance_arrays([done[i] for i in tried], (task.T + 1, task.nx)))
        arrays["inst_index"] = np.asarray(tried, dtype=int)
    dims = task.dims()
    arrays, timing = split_timing(arrays)   # clock readings go to the timing sidecar
    # the policy relative to the dataset's folder (as a checkpoint records its dataset): clone-independent bytes
    policy = portable_path(config.policy, Path(out).parent) if config.policy else None
    path = save_npz(out, arrays, kind="dataset",
                    config={**asdict(config), "policy": policy, "workers": described.get("workers"), "executor": described},
                    task=config.task, task_options=config.task_options, task_params=task.params(), dims=dims,
                    stats={"attempts": stats.attempts, "kept": len(kept), "rejected": stats.rejected,
                           "convergence_rate": stats.convergence_rate},
                    timing={**timing, "mean_solve_time": stats.mean_solve_time, "attempts": stats.attempts,
                            "wall_time": stats.wall_time})
    store.remove()
    return path, stats

"""Where independent jobs run: in-process, a local process pool, or a Dask cluster.

    from sdp_cli.execution.executor import make_executor
    with make_executor("local", workers=4) as ex:            # or "dask", scheduler="tcp://host:8786"
        ex.warm(build_solver, "pendulum", {}, 1000)           # once per worker process
        futs = {ex.submit(fn, *args): i for i, args in enumerate(argsets)}
        while futs:
            for f in ex.wait_any(list(futs)):                 # at least one finished job
                i, out = futs.pop(f), ex.outcome(f)           # Outcome(value | error | lost)

Backends (:func:`make_executor`):

- ``local``, 1 worker: :class:`SerialExecutor`, jobs run in this process one at a time,
  lazily, inside :meth:`~Executor.wait_any` (so each result can be persisted before the
  next job starts);
- ``local``, N workers: :class:`PoolExecutor`, a ``ProcessPoolExecutor`` (fork context
  where available, so what :meth:`~Executor.warm` built in the parent is inherited);
- ``dask``: :class:`DaskExecutor`, a ``dask.distributed.Client`` of the scheduler at
  ``scheduler`` (``tcp://HOST:PORT``), or of a ``LocalCluster`` of ``workers`` processes
  with one thread each, on loopback, started here and closed on exit.

Failure semantics, the same for every backend (:meth:`Executor.outcome`):

- an exception raised by the job function is its result: ``Outcome(error=exc)``; callers
  record it as a failed attempt and go on;
- a job whose worker process died is ``Outcome(lost=True)``: callers submit it again.
  Dask reschedules tasks of lost workers itself; a task that killed
  ``distributed.scheduler.allowed-failures`` workers, or a local pool broken more than
  ``max_restarts`` times, is an :class:`~sdp_cli.errors.SdpError` (never a silent change
  of the results).

Jobs should be module-level functions of small arguments; state that is expensive to
build (the casadi solver) is cached per process by the job itself (``get_solver``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import FIRST_COMPLETED, Future
from concurrent.futures import wait as _cf_wait
from concurrent.futures.process import BrokenProcessPool
from concurrent.futures import ProcessPoolExecutor

from sdp_cli.errors import SdpError
from sdp_cli.execution.executor_base import Executor, Outcome, error_status  # noqa: F401 (re-exported)

KINDS = ("local", "dask")


# ------------------------------------------------------------------ serial
class _Deferred:
    """A job run later, in this process (the serial executor's future)."""

    __slots__ = ("fn", "args", "done", "value", "error")

    def __init__(self, fn, args):
        self.fn, self.args, self.done, self.value, self.error = fn, args, False, None, None

    def run(self) -> None:
        try:
            self.value = self.fn(*self.args)
        except Exception as e:  # noqa: BLE001 - a job's exception is its outcome
            self.error = e
        self.done = True

    def cancel(self) -> bool:
        return not self.done


class SerialExecutor(Executor):
    """Jobs run in this process, one at a time, when :meth:`wait_any` asks for one."""

    kind = "local"

    @property
    def max_inflight(self) -> int | None:
        return None

    def submit(self, fn, *args) -> _Deferred:
        return _Deferred(fn, args)

    def wait_any(self, futures: list) -> list:
        done = [f for f in futures if f.done]
        if done or not futures:
            return done
        futures[0].run()
        return [futures[0]]

    def outcome(self, fut: _Deferred) -> Outcome:
        return Outcome(value=fut.value, error=fut.error)


# -------------------------------------------------------------- local pool
class PoolExecutor(Executor):
    """A ``ProcessPoolExecutor`` of ``workers`` processes, created at the first submit."""

    kind = "local"

    def __init__(self, workers: int, max_restarts: int = 3):
        self.workers, self.max_restarts = int(workers), int(max_restarts)
        self.restarts = 0
        self._pool = None
        self._broken = False

    def slots(self) -> int:
        return self.workers

    def _ensure_pool(self):
        if self._pool is not None and self._broken:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            self.restarts += 1
            if self.restarts > self.max_restarts:
                raise SdpError(f"local worker processes died {self.restarts} times (out of memory, or a "
                               "crash in the solver?); finished results are kept, re-run to resume")
        if self._pool is None:
            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            from sdp_cli.execution.workers import worker_init

            self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=worker_init,
                                             initargs=(os.getpid(),))
            self._broken = False
        return self._pool

    def submit(self, fn, *args) -> Future:
        try:
            return self._ensure_pool().submit(fn, *args)
        except BrokenProcessPool:  # broke before any of its futures told us
            self._broken = True
            return self._ensure_pool().submit(fn, *args)

    def wait_any(self, futures: list) -> list:
        return list(_cf_wait(futures, return_when=FIRST_COMPLETED).done) if futures else []

    def outcome(self, fut: Future) -> Outcome:
        if fut.cancelled():
            return Outcome(lost=True)
        err = fut.exception()
        if isinstance(err, BrokenProcessPool):
            self._broken = True
            return Outcome(lost=True)
        return Outcome(value=None if err else fut.result(), error=err)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt) and self._pool is not None:
            # Ctrl-C: the workers ignore SIGINT (no tracebacks from each of them); stop them now instead of
            # waiting for their solves (SIGTERM: a solve dies at once, its result was not persisted and a re-run
            # redoes it; a training job writes its checkpoint at the next step boundary and exits,
            # sdp_cli.execution.interrupts), and wait for them so that no worker outlives this process.
            procs = list(getattr(self._pool, "_processes", {}).values())
            for p in procs:
                p.terminate()
            for p in procs:
                p.join(timeout=30)
                if p.is_alive():
                    p.kill()
            manager = getattr(self._pool, "_executor_manager_thread", None)
            self._pool.shutdown(wait=False, cancel_futures=True)
            if manager is not None:
                # let the pool's manager thread see its dead workers and close its wakeup pipe before the
                # interpreter exits: else (Python 3.11) the exit hook may write to that pipe as it closes,
                # and print "Exception ignored ... Bad file descriptor" after "Interrupted."
                manager.join(timeout=30)
            self._pool = None
            return
        self.close()


def check_executor_options(kind: str | None, workers: int | None, scheduler: str | None) -> str:
    """Validate the options of :func:`make_executor` (cheap, starts nothing); the resolved kind."""
    kind = kind or ("dask" if scheduler else "local")
    if kind not in KINDS:
        raise SdpError(f"unknown executor {kind!r}; valid executors: {', '.join(KINDS)}")
    if workers is not None and workers <= 0:
        raise SdpError(f"--workers must be > 0, got {workers}")
    if scheduler and kind != "dask":
        raise SdpError("--scheduler needs --executor dask")
    if scheduler and workers is not None:
        raise SdpError("--workers sizes a local pool or LocalCluster; with --scheduler the cluster's "
                       "workers are used")
    return kind


def make_executor(kind: str | None = "local", workers: int | None = None, scheduler: str | None = None,
                  **dask_options) -> Executor:
    """An executor of ``kind`` (``local`` or ``dask``; ``None``: dask if ``scheduler`` else local).

    ``workers``: processes of the local pool or of the Dask ``LocalCluster`` (default: all
    cores; 1 with ``local`` runs jobs in this process). ``scheduler``: address of a running
    Dask scheduler (``tcp://HOST:PORT``); its workers are used, so ``workers`` must be None.
    ``dask_options``: ``connect_timeout``, ``worker_timeout`` (seconds).
    """
    kind = check_executor_options(kind, workers, scheduler)
    if kind == "dask":
        from sdp_cli.execution.executor_dask import DaskExecutor

        return DaskExecutor(workers, scheduler, **dask_options)
    workers = max(1, workers or os.cpu_count() or 1)
    return SerialExecutor() if workers == 1 else PoolExecutor(workers)

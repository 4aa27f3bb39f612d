"""Where independent jobs run: in-process, a local process pool, or a Dask cluster.

    from sdp_cli.executor import make_executor
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

import logging
import multiprocessing as mp
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future
from concurrent.futures import wait as _cf_wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from sdp_cli.errors import SdpError

KINDS = ("local", "dask")


@dataclass
class Outcome:
    """What became of one job: its ``value``, the ``error`` it raised, or ``lost`` (retry it)."""

    value: Any = None
    error: BaseException | None = None
    lost: bool = False

    @property
    def ok(self) -> bool:
        return self.error is None and not self.lost


def error_status(err: BaseException) -> str:
    """One line describing a job's exception (stored as a failed attempt's ``status``)."""
    msg = " ".join(str(err).split())
    return f"error: {type(err).__name__}: {msg}"[:300]


class Executor:
    """Common interface; see the module docstring."""

    kind = "?"

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        pass

    def slots(self) -> int:
        """Jobs that run at the same time right now."""
        return 1

    @property
    def max_inflight(self) -> int | None:
        """How many jobs to keep submitted (``None``: no limit, jobs run lazily one by one)."""
        return 2 * self.slots()

    def describe(self) -> dict:
        """JSON-able description recorded in artifacts."""
        return {"kind": self.kind, "workers": self.slots()}

    def warm(self, fn: Callable, *args) -> None:
        """Run ``fn(*args)`` once where jobs will run (e.g. build a solver), before any job."""
        fn(*args)

    def submit(self, fn: Callable, *args):
        raise NotImplementedError

    def wait_any(self, futures: list) -> list:
        """Block until at least one of ``futures`` is finished; return the finished ones."""
        raise NotImplementedError

    def outcome(self, fut) -> Outcome:
        raise NotImplementedError

    def cancel(self, futures: Iterable) -> None:
        for f in futures:
            f.cancel()

    def imap_unordered(self, fn: Callable, argsets: list[tuple], max_inflight: int | None = None
                       ) -> Iterator[tuple[int, Outcome]]:
        """``(i, Outcome)`` of ``fn(*argsets[i])`` for every i, in completion order.

        At most ``max_inflight`` jobs are submitted at once (default :attr:`max_inflight`);
        lost jobs are resubmitted, so every index is yielded exactly once with a value or an error.
        """
        pending = list(range(len(argsets)))[::-1]
        inflight: dict[Any, int] = {}
        try:
            while pending or inflight:
                limit = max_inflight or self.max_inflight or len(argsets)
                while pending and len(inflight) < limit:
                    i = pending.pop()
                    inflight[self.submit(fn, *argsets[i])] = i
                for f in sorted(self.wait_any(list(inflight)), key=inflight.get):
                    i = inflight.pop(f)
                    out = self.outcome(f)
                    if out.lost:
                        pending.append(i)
                    else:
                        yield i, out
        finally:
            self.cancel(list(inflight))


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
        from concurrent.futures import ProcessPoolExecutor

        if self._pool is not None and self._broken:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            self.restarts += 1
            if self.restarts > self.max_restarts:
                raise SdpError(f"local worker processes died {self.restarts} times (out of memory, or a "
                               "crash in the solver?); finished results are kept, re-run to resume")
        if self._pool is None:
            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            from sdp_cli.workers import worker_init

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


# -------------------------------------------------------------------- dask
def _probe() -> dict:
    """Run on every Dask worker: can it import sdp, and which version."""
    import sdp_cli

    return {"version": sdp_cli.__version__, "pid": os.getpid()}


class DaskExecutor(Executor):
    """Jobs as ``dask.distributed`` tasks (one thread per worker process)."""

    kind = "dask"

    def __init__(self, workers: int | None = None, scheduler: str | None = None,
                 connect_timeout: float = 10.0, worker_timeout: float = 60.0):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise SdpError("--executor dask needs dask.distributed: pip install 'dask[distributed]'") from None
        self.scheduler, self.cluster, self.client = scheduler, None, None
        self._nthreads, self._nthreads_at = 0, -1e9
        # a LocalCluster's nannies write their pre-spawn environment (OMP_NUM_THREADS=1, ...) into
        # this process's os.environ, at start and at every worker restart: restored after both
        self._environ = dict(os.environ)
        try:
            if scheduler:
                self.client = Client(scheduler, timeout=connect_timeout, set_as_default=False)
            else:
                n = max(1, workers or os.cpu_count() or 1)
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
                self.client = Client(self.cluster, set_as_default=False)
                self._restore_environ()
        except (OSError, TimeoutError, ValueError) as e:
            self.close()
            where = f"the dask scheduler at {scheduler}" if scheduler else "a dask LocalCluster"
            raise SdpError(f"cannot connect to {where}: {' '.join(str(e).split()) or type(e).__name__}") from None
        try:
            self._check_workers(worker_timeout)
        except BaseException:
            self.close()
            raise

    def _check_workers(self, timeout: float) -> None:
        import sdp_cli

        try:
            self.client.wait_for_workers(1, timeout=timeout)
        except TimeoutError:
            raise SdpError(f"no dask worker joined the scheduler at {self.scheduler} within {timeout:g} s; "
                           "start some with `dask worker <scheduler address>`") from None
        for addr, info in self.client.run(_probe, on_error="return").items():
            if isinstance(info, BaseException):
                raise SdpError(f"dask worker {addr} cannot run sdp jobs ({error_status(info)}); install this "
                               "sdp version in the workers' environment") from None
            if info["version"] != sdp_cli.__version__:
                raise SdpError(f"dask worker {addr} runs sdp {info['version']}, this client "
                               f"{sdp_cli.__version__}; use the same version everywhere")

    def slots(self) -> int:
        now = time.monotonic()
        if now - self._nthreads_at > 2.0:  # the cluster may grow or shrink; ask at most every 2 s
            self._nthreads = sum(self.client.nthreads().values())
            self._nthreads_at = now
        return max(1, self._nthreads)

    def describe(self) -> dict:
        return {"kind": self.kind, "workers": self.slots(), "scheduler": self.client.scheduler.address}

    def warm(self, fn, *args) -> None:
        """``fn(*args)`` as one task per current worker, in parallel; an error is an SdpError.

        Tasks rather than ``client.run``: a long build (JIT compilation) then runs in the
        worker's thread, not in its event loop, and heartbeats go on. Workers that join
        later build on first use. Catching a broken worker environment here keeps it from
        being recorded as failed solves.
        """
        from distributed import wait

        futs = {self.client.submit(fn, *args, workers=[addr], allow_other_workers=True, pure=False): addr
                for addr in self.client.nthreads()}
        with self.client.as_current():
            wait(list(futs))
        for f, addr in futs.items():
            if f.status == "error":
                raise SdpError(f"dask worker {addr} cannot build the solver ({error_status(f.exception())})")

    def run_on_workers(self, fn: Callable, *args) -> dict:
        """``{worker address: fn(*args)}`` on every worker process (``client.run``)."""
        return self.client.run(fn, *args)

    def worker_pids(self) -> dict:
        return {a: r["pid"] for a, r in self.client.run(_probe).items()}

    def submit(self, fn, *args):
        return self.client.submit(fn, *args, pure=False)

    def wait_any(self, futures: list) -> list:
        from distributed import wait

        if not futures:
            return []
        try:
            with self.client.as_current():
                return list(wait(futures, return_when="FIRST_COMPLETED").done)
        except Exception:  # noqa: BLE001 - FuturesCancelledError: cancelled futures are finished too
            done = [f for f in futures if f.status != "pending"]
            if not done:
                raise
            return done

    def outcome(self, fut) -> Outcome:
        from distributed import KilledWorker

        st = fut.status
        if st == "finished":
            try:
                return Outcome(value=fut.result())
            except Exception:  # noqa: BLE001 - result lost in transit: compute it again
                return Outcome(lost=True)
        if st == "error":
            err = fut.exception()
            if isinstance(err, KilledWorker):
                raise SdpError(f"a job was lost with every dask worker it ran on ({error_status(err)[7:]}); "
                               "finished results are kept, re-run to resume") from None
            return Outcome(error=err)
        return Outcome(lost=True)  # cancelled / lost

    def cancel(self, futures: Iterable) -> None:
        futures = list(futures)
        if futures and self.client is not None and self.client.status == "running":
            self.client.cancel(futures)

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None
        self._restore_environ()

    def _restore_environ(self) -> None:
        if os.environ != self._environ:
            os.environ.clear()
            os.environ.update(self._environ)


# ------------------------------------------------------------------ factory
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
        return DaskExecutor(workers, scheduler, **dask_options)
    workers = max(1, workers or os.cpu_count() or 1)
    return SerialExecutor() if workers == 1 else PoolExecutor(workers)

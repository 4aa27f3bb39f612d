"""The Dask backend of :mod:`sdp_cli.execution.executor` (``--executor dask``, ``--scheduler ADDR``): jobs as
``dask.distributed`` tasks; the failure semantics are the executor module's."""

from __future__ import annotations

import logging
import os
import time
from typing import Callable, Iterable

from sdp_cli.errors import SdpError
from sdp_cli.execution.executor_base import Executor, Outcome, error_status
import sdp_cli

def _probe() -> dict:
    """Run on every Dask worker: can it import sdp, and which version."""
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

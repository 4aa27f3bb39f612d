"""The executor interface (:class:`Executor`, :class:`Outcome`) shared by the local backends
(:mod:`sdp_cli.execution.executor`) and the Dask one (:mod:`sdp_cli.execution.executor_dask`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

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

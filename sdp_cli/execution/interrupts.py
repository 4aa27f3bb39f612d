"""Interrupts at clean boundaries: Ctrl-C (SIGINT) and SIGTERM (what schedulers send) during training.

A signal that lands in the middle of a training step leaves the random generator, the weights or the
optimizer half-way through it, so a checkpoint written there does not resume bit-for-bit. Inside
:func:`deferred`, SIGINT and SIGTERM only set a flag; the training loop checks it between steps
(:meth:`Deferred.check`), writes its checkpoint at that step boundary and raises ``KeyboardInterrupt``,
which the CLI turns into "Interrupted." and exit code 130. Ctrl-C again while one is pending interrupts at
once (an impatient user is never ignored); any other signal does not: a pool worker gets the terminal's SIGINT
and then its parent's SIGTERM, and a second SIGTERM when the pool sees a sibling worker exit first (Python's
process pool terminates every worker of a broken pool), and must still stop at a boundary.
Outside the main thread (where Python cannot install handlers) nothing is deferred, and a signal the process
ignores (``nohup ... &`` ignores SIGINT; so do pool workers, whose parent handles Ctrl-C) stays ignored.
"""

from __future__ import annotations

import contextlib
import signal
import threading

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Deferred:
    """The pending signal, if any (set by the handler, read between steps)."""

    def __init__(self):
        self.signum: int | None = None

    @property
    def pending(self) -> bool:
        return self.signum is not None

    def check(self, before_raise=None) -> None:
        """If a signal is pending: call ``before_raise`` (e.g. write a checkpoint), then raise ``KeyboardInterrupt``."""
        if self.pending:
            if before_raise is not None:
                before_raise()
            raise KeyboardInterrupt(f"signal {self.signum}")


@contextlib.contextmanager
def deferred():
    """Defer SIGINT and SIGTERM to :meth:`Deferred.check` within the block."""
    state = Deferred()
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum, frame):
        if state.signum == signum == signal.SIGINT:   # Ctrl-C, Ctrl-C: stop now
            raise KeyboardInterrupt(f"signal {signum}")
        if state.signum is None:
            state.signum = signum

    old = {s: signal.signal(s, handler) for s in SIGNALS if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)

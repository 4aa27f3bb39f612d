"""A wall-clock limit on solver calls: a forked solver process, killed and re-forked past the limit.

fatrop has no time limit (casadi's fatrop interface accepts neither ``max_wall_time`` nor
``max_cpu_time``), and it can run without end: a non-finite or absurd guess is refused before the
solver starts (:meth:`TrajOptSolver.solve_from`), but a finite, moderate guess hung one collection
of the double pendulum loop for more than 40 minutes before this guard existed (fig2, seed 2,
iteration 3). That case is reproducible and the guess was the naive one, not the policy's: TO from
the naive guess on instance 16 of that collection (xi = (3.2693370019778207, -0.40105812656296724,
0, 0)) enters fatrop 1.1.8's restoration phase at iteration 21, and after iteration 24r (constraint
violation 9e4) never returns; the same xi rounded to float32 ends after 20 iterations
(LocalInfeasibility). Under this guard the fig2 runs of seed 2 stop it at 300.1 s and record it as
not converged (tests/test_solve_timeout.py solves it with a 3 s limit). A blocking C call cannot be interrupted from Python inside
its process, so the calls run in a child process forked from the one that built the solver
(:class:`ForkServer`: the solver and its compiled functions are inherited, nothing is rebuilt),
one request at a time through pipes. Past the limit the child is killed, :class:`SolveTimeout`
raised, and the next call forks a fresh child. The child lives as long as its server (it exits
when the parent's end of the pipe closes), so the copy-on-write cost of a fork is paid once, not
per solve: solve times measured in the child equal those measured in the parent.

The limit is ``SDP_SOLVE_TIMEOUT`` seconds (default :data:`DEFAULT_TIMEOUT`; 0 runs the calls in
this process, unguarded). On platforms without ``fork`` the calls are not guarded.
"""

from __future__ import annotations

import math
import os
import pickle
import select
import signal
import struct
import time
from typing import Any, Callable
from sdp_cli.errors import SdpError

DEFAULT_TIMEOUT = 300.0   #: seconds; a quadrotor-9 solve takes about 0.6 s, the slowest seen about 30 s
_LEN = struct.Struct("!Q")


class SolveTimeout(Exception):
    """The call ran past its wall-clock limit and its process was killed."""


def solve_timeout() -> float:
    """The limit in seconds from ``SDP_SOLVE_TIMEOUT`` (0: unguarded)."""
    raw = os.environ.get("SDP_SOLVE_TIMEOUT", "")
    if not raw.strip():
        return DEFAULT_TIMEOUT
    try:
        value = float(raw)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value >= 0):   # a typo is one clear error, not the default in silence
        raise SdpError(f"SDP_SOLVE_TIMEOUT must be a number of seconds >= 0 (0: unguarded), got {raw!r}")
    return value


def _send(fd: int, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_LEN.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def _read_exact(fd: int, n: int, deadline: float | None) -> bytes | None:
    """``n`` bytes from ``fd``; None at end of file; :class:`SolveTimeout` past ``deadline``."""
    buf = bytearray()
    while len(buf) < n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise SolveTimeout
        b = os.read(fd, min(n - len(buf), 1 << 20))
        if not b:
            return None
        buf += b
    return bytes(buf)


def _recv(fd: int, deadline: float | None = None) -> Any:
    head = _read_exact(fd, _LEN.size, deadline)
    if head is None:
        raise EOFError
    body = _read_exact(fd, _LEN.unpack(head)[0], deadline)
    if body is None:
        raise EOFError
    return pickle.loads(body)


class ForkServer:
    """Runs ``handler(*args)`` in a forked child, one call at a time, with a wall-clock limit."""

    def __init__(self, handler: Callable[..., Any]):
        self.handler = handler
        self._pid: int | None = None
        self._to = self._from = -1
        self._owner = os.getpid()

    def _start(self) -> None:
        r_req, w_req = os.pipe()
        r_rep, w_rep = os.pipe()
        pid = os.fork()
        if pid == 0:                          # child: serve until the parent closes its end
            code = 0
            try:
                os.close(w_req)
                os.close(r_rep)
                while True:
                    try:
                        args = _recv(r_req)
                    except EOFError:
                        break
                    try:
                        out = ("ok", self.handler(*args))
                    except BaseException as e:     # noqa: BLE001 - everything goes back to the parent
                        out = ("err", f"{type(e).__name__}: {e}")
                    _send(w_rep, out)
            except BaseException:                  # noqa: BLE001
                code = 1
            finally:
                os._exit(code)
        os.close(r_req)
        os.close(w_rep)
        self._pid, self._to, self._from, self._owner = pid, w_req, r_rep, os.getpid()

    def stop(self) -> None:
        if self._pid is None:
            return
        for fd in (self._to, self._from):
            try:
                os.close(fd)
            except OSError:
                pass
        if self._owner == os.getpid():
            try:
                os.kill(self._pid, signal.SIGKILL)
                os.waitpid(self._pid, 0)
            except (ProcessLookupError, ChildProcessError):
                pass
        self._pid = None

    def call(self, args: tuple, timeout: float) -> Any:
        """``handler(*args)``: its result, a ``RuntimeError`` for what it raised, or
        :class:`SolveTimeout` past ``timeout`` seconds (``<= 0``: run here, unguarded)."""
        if timeout <= 0 or not hasattr(os, "fork"):
            return self.handler(*args)
        if self._pid is not None and self._owner != os.getpid():
            self._pid = None                   # inherited from the process we were forked from: not ours
        if self._pid is None:
            self._start()
        try:
            _send(self._to, args)
            status, value = _recv(self._from, time.monotonic() + timeout)
        except SolveTimeout:
            self.stop()
            raise SolveTimeout(f"the solver ran past the {timeout:g} s limit (SDP_SOLVE_TIMEOUT) and was "
                               "stopped") from None
        except (EOFError, OSError) as e:
            self.stop()
            raise RuntimeError(f"the solver process died ({type(e).__name__})") from None
        if status == "err":
            raise RuntimeError(value)
        return value

    def __del__(self):   # pragma: no cover - interpreter shutdown order varies
        try:
            self.stop()
        except Exception:
            pass

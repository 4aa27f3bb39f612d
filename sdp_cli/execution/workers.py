"""Set-up of local pool worker processes: one BLAS thread each, and no orphans.

A worker started by ``sdp collect``/``sdp refine`` must not outlive its parent: after a
``kill -9`` of the parent, ProcessPoolExecutor's own shutdown never runs.
"""

from __future__ import annotations

import os
import time
import signal
import threading


def worker_init(parent: int | None = None) -> None:
    # one BLAS/OpenMP thread per worker: the parallelism is across processes
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # Ctrl-C reaches the whole foreground process group: the parent handles it (and stops the pool), so a
    # worker ignores it instead of printing its own KeyboardInterrupt traceback. Training inside a worker
    # (`sdp pipeline --run`) installs its own handler (sdp_cli.execution.interrupts) and checkpoints at a step boundary.

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(parent)


def die_with_parent(parent: int | None) -> None:
    """Make this worker exit when the process that started it dies (``kill -9`` included).

    Linux: ``prctl(PR_SET_PDEATHSIG, SIGKILL)``; elsewhere a daemon thread polls the parent pid.
    """
    if parent is None:
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0:   # PR_SET_PDEATHSIG
            if os.getppid() != parent:                          # died before prctl took effect
                os._exit(1)
            return
    except (OSError, AttributeError):
        pass

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()

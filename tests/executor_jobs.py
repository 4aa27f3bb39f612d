"""Job functions for the executor tests (module-level, so that workers can run them).

Dask workers cannot import this file: the Dask tests ship it by value
(``cloudpickle.register_pickle_by_value``).
"""

from __future__ import annotations

import os

import numpy as np

from sdp_cli.algorithm import collect as collect_mod
from sdp_cli.data.artifacts import load_npz
from sdp_cli.algorithm.collect import solve_index

BAD = 1  # the index whose job raises in the failure tests


def square_or_raise(x):
    if x == 3:
        raise ValueError("three is not allowed")
    return x * x


def exit_once(x, marker):
    """Kill the worker process the first time it runs with ``x == 0``."""
    if x == 0 and not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(1)
    return x + 100


def always_exit(x):
    os._exit(1)


def solve_or_raise(task_name, task_options, seed, index, max_iter):
    if index == BAD:
        raise RuntimeError("worker-side failure")
    return [solve_index(task_name, task_options, seed, index, max_iter)]


def flaky_jobs(monkeypatch):
    """Make collect's naive-guess jobs raise on index BAD (jobs are ``(fn, args, indices)``, results lists)."""
    def make(self, indices):
        c = self.config
        return [(solve_or_raise, (c.task, c.task_options, c.seed, i, c.max_iter), [i]) for i in indices]

    monkeypatch.setattr(collect_mod._Jobs, "make", make)


def assert_same_dataset(p, q) -> dict:
    a, _ = load_npz(p)
    b, _ = load_npz(q)
    assert np.array_equal(a["index"], b["index"])
    np.testing.assert_allclose(a["X"], b["X"], atol=1e-8)
    np.testing.assert_allclose(a["K"], b["K"], atol=1e-6)
    return a


def die_once_after_training(marker, config, out, device="auto"):
    """`sdp_cli.experiments.runner.run_job`, but the first call (per marker) kills its worker process as soon as the
    run's training has finished, before its evaluation: the runner must redo (resume) that run."""
    import threading
    import time
    from pathlib import Path

    from sdp_cli.experiments.runner import run_job

    if not os.path.exists(marker):
        open(marker, "w").close()

        def kill_when_trained():
            while not (Path(out) / "it0" / "policy" / "checkpoint.pt").exists():
                time.sleep(0.02)
            os._exit(1)

        threading.Thread(target=kill_when_trained, daemon=True).start()
    return run_job(config, out, device)

"""Suite-wide hooks: the test order is random and modules run on 2 processes (pyproject addopts: pytest-xdist,
``--dist loadscope``); say which order ran, so that an order-dependent failure can be replayed in one process
with ``-n 0 --random-order-seed=N``."""

from __future__ import annotations

import os

import pytest

# casadi code compiled at gcc -O0 in the tests and every command they run: the quadrotor's and UR5's functions
# compile 5-12x faster (the default suite compiles ~200 s of them at -O2 with a cold cache, as on CI) and compute
# the same bits (tests/test_trajopt.py::test_every_optimization_level_computes_the_same_bits); run with
# SDP_JIT_OPT=-O2 to test the default level. test_regression_small's `dvc repro` runs at the user's default.
os.environ.setdefault("SDP_JIT_OPT", "-O0")


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Every test: one torch thread (tiny networks; a shared 2-core machine), restored after the test."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    seed = getattr(config.option, "random_order_seed", None)
    seed = str(seed).removeprefix("default:") if seed is not None else None
    bucket = str(getattr(config.option, "random_order_bucket", "module")).removeprefix("default:")
    if seed is not None:
        terminalreporter.write_line(f"test order: --random-order-bucket={bucket} --random-order-seed={seed}"
                                    " (in one process: add -n 0)")

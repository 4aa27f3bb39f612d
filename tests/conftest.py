"""Suite-wide hooks: the test order is random (pyproject addopts); say which order ran, so that an
order-dependent failure can be replayed with ``--random-order-seed=N``."""

from __future__ import annotations

import pytest


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
        terminalreporter.write_line(f"test order: --random-order-bucket={bucket} --random-order-seed={seed}")

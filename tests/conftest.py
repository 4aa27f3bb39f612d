"""Suite-wide hooks: the test order is random (pyproject addopts); say which order ran, so that an
order-dependent failure can be replayed with ``--random-order-seed=N``."""

from __future__ import annotations


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    seed = getattr(config.option, "random_order_seed", None)
    seed = str(seed).removeprefix("default:") if seed is not None else None
    bucket = str(getattr(config.option, "random_order_bucket", "module")).removeprefix("default:")
    if seed is not None:
        terminalreporter.write_line(f"test order: --random-order-bucket={bucket} --random-order-seed={seed}")

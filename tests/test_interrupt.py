"""Interrupted and resumed means identical: Ctrl-C (SIGINT) or SIGTERM at any moment of `sdp train`, then
`--resume`, gives the metrics and the checkpoint bytes of an uninterrupted run.

At 38d2c04 the checkpoint written at a Ctrl-C held a random state already advanced into the next step
(final loss 0.000255 / 0.000263 against 0.000253), and a resumed checkpoint's bytes differed from an
uninterrupted one's (pickle memo of the optimizer's `step` tensors)."""

from __future__ import annotations

import csv
import os
import signal
import threading

import pytest

from sdp_cli.policy.checkpoint import load_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.train import train
from synthetic_dataset import one_torch_thread, write_dataset  # noqa: F401 (autouse fixture)

TINY = dict(T_h=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=8, checkpoint_every_s=1e9)


def quiet(*_):
    pass


def metrics(run):
    with open(run / "metrics.csv", newline="") as f:
        return [(r["step"], r["loss"], r["sobolev"], r["grad_norm"]) for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("intr") / "p.npz", "pendulum", n_traj=3, seed=0, T=30)


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory):
    import torch

    out = tmp_path_factory.mktemp("ref") / "run"
    cfg = TrainConfig(method="sdp", epochs=60, **TINY)
    n = torch.get_num_threads()
    torch.set_num_threads(1)       # as the tests (the autouse fixture is per test)
    try:
        train(data, out, cfg, device="cpu", progress=False, log=quiet)
    finally:
        torch.set_num_threads(n)
    return cfg, out


@pytest.mark.parametrize("sig,delay", [(signal.SIGINT, 0.25), (signal.SIGINT, 0.6), (signal.SIGTERM, 0.4)])
def test_signal_mid_training_then_resume_is_bit_identical(data, reference, tmp_path, sig, delay):
    cfg, ref = reference
    out = ref.parent / f"{tmp_path.name}-run"     # beside the reference: the same relative dataset path
    steps = []
    timer = threading.Timer(delay, os.kill, (os.getpid(), sig))   # lands wherever the step is
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            train(data, out, cfg, device="cpu", progress=False, log=quiet, on_step=steps.append)
    finally:
        timer.cancel()
    stopped = load_checkpoint(out)["step"]
    assert 0 < stopped < load_checkpoint(ref)["step"] and stopped == steps[-1]     # at the step boundary
    train(data, out, cfg, device="cpu", resume=True, progress=False, log=quiet)
    assert metrics(out) == metrics(ref)
    assert (out / "checkpoint.pt").read_bytes() == (ref / "checkpoint.pt").read_bytes()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler          # handlers restored

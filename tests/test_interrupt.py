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
from sdp_cli.training.train import train
from synthetic_dataset import write_dataset

TINY = dict(horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=8, checkpoint_every_s=1e9)


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
    cfg = TrainConfig.of(method="sdp", epochs=60, **TINY)
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
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    if signal.getsignal(sig) is signal.SIG_IGN:   # run in a background job: a SIGINT this process ignores stays so
        pytest.skip(f"signal {sig} is ignored by this process (started in the background)")
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
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before   # handlers restored


class _Killed(BaseException):
    """Stands for kill -9: nothing after the raise runs (no handler, no final checkpoint)."""


@pytest.mark.parametrize("after", ["metrics", "checkpoint"])
def test_a_kill_between_the_writes_of_a_checkpoint_then_resume_is_identical(data, tmp_path, monkeypatch, after):
    """kill -9 lands anywhere, also between a periodic checkpoint's writes (checkpoint.pt, then metrics.csv
    when they were written in that order: the metrics rows since the last flush were lost for good, seen as
    rows 47-64 missing after a resume). Killed right after either write of the 5th checkpoint, `--resume`
    must give the metrics and checkpoint bytes of an uninterrupted run."""
    import sdp_cli.training.train as train_mod
    from sdp_cli.data.metrics_log import MetricsLog

    cfg = TrainConfig.of(method="sdp", epochs=20, **{**TINY, "checkpoint_every_s": 0.0})
    ref = train(data, tmp_path / "ref", cfg, device="cpu", progress=False, log=quiet).parent
    out = tmp_path / "run"
    calls = []

    def killing(real):
        def wrapped(*a, **k):
            res = real(*a, **k)
            calls.append(1)
            if len(calls) == 5:
                raise _Killed
            return res
        return wrapped

    if after == "checkpoint":
        monkeypatch.setattr(train_mod, "save_checkpoint", killing(train_mod.save_checkpoint))
    else:
        monkeypatch.setattr(MetricsLog, "rewrite", killing(MetricsLog.rewrite))
    with pytest.raises(_Killed):
        train(data, out, cfg, device="cpu", progress=False, log=quiet)
    monkeypatch.undo()
    assert 0 < load_checkpoint(out)["step"] < load_checkpoint(ref)["step"]
    train(data, out, cfg, device="cpu", resume=True, progress=False, log=quiet)
    assert metrics(out) == metrics(ref)
    assert (out / "checkpoint.pt").read_bytes() == (ref / "checkpoint.pt").read_bytes()


def test_ctrl_c_during_a_loop_then_the_same_command_gives_the_same_results(tmp_path):
    """`sdp loop`, Ctrl-C while it trains, then the same command: the same evaluation as an uninterrupted loop
    (at 38d2c04: iteration 0's policy cost 16.943 against 17.187)."""
    import time

    import pandas as pd

    from sdp_cli.algorithm.loop import LoopConfig, LoopRolloutConfig, run_loop

    train = TrainConfig.of(method="sdp", epochs=150, horizon=8, batch_size=8, down_dims=[8, 16], n_groups=4,
                           step_embed_dim=8)
    cfg = LoopConfig(task="pendulum", train=train, rollout=LoopRolloutConfig(t_a=4, n_test=3, eval_refine=False),
                     n_traj=(2,), workers=1)
    ref = run_loop(cfg, tmp_path / "ref", log=quiet)
    out = tmp_path / "run"

    def interrupt_when_training():
        t0 = time.time()
        while not (out / "it0" / "policy" / "metrics.csv").exists() and time.time() - t0 < 60:
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        pytest.skip("SIGINT is ignored by this process (started in the background)")
    watcher = threading.Thread(target=interrupt_when_training, daemon=True)
    watcher.start()
    with pytest.raises(KeyboardInterrupt):
        run_loop(cfg, out, log=quiet)
    watcher.join()
    ck = load_checkpoint(out / "it0" / "policy")
    assert not ck["finished"] and 0 < ck["step"] < ck["total_steps"]          # interrupted mid-training
    got = run_loop(cfg, out, log=quiet)
    cols = ["iteration", "policy_cost_mean", "success_rate"]
    pd.testing.assert_frame_equal(got[cols], ref[cols])
    assert metrics(out / "it0" / "policy") == metrics(tmp_path / "ref" / "it0" / "policy")


def test_only_ctrl_c_twice_interrupts_at_once():
    """A pool worker gets SIGTERM from its parent, and again when the pool sees a sibling worker exit first: the
    second SIGTERM must not cut its checkpoint short; Ctrl-C twice (an impatient user) still stops at once."""
    import time

    from sdp_cli.execution.interrupts import deferred

    before = signal.getsignal(signal.SIGINT)
    if before is signal.SIG_IGN:                              # (a suite run in the background ignores SIGINT)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _twice(deferred, time)
    finally:
        signal.signal(signal.SIGINT, before)


def _twice(deferred, time):
    with deferred() as interrupt:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)                 # pending, not raised
        assert interrupt.pending and interrupt.signum == signal.SIGTERM
        saved = []
        with pytest.raises(KeyboardInterrupt):
            interrupt.check(lambda: saved.append(True))
        assert saved == [True]
    with pytest.raises(KeyboardInterrupt):
        with deferred():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)              # raised at once
            time.sleep(1)

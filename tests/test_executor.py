"""Local executors (in-process, process pool): streaming, job errors, dead workers, options."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from executor_jobs import always_exit, exit_once, flaky_jobs, square_or_raise
from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.algorithm.collect import CollectConfig, collect
from sdp_cli.errors import SdpError
from sdp_cli.execution.executor import PoolExecutor, SerialExecutor

runner = CliRunner()


# ------------------------------------------------------------------- local
@pytest.mark.parametrize("ex", [SerialExecutor(), PoolExecutor(2)], ids=["serial", "pool"])
def test_local_executors_stream_values_and_errors(ex):
    with ex:
        got = dict(ex.imap_unordered(square_or_raise, [(i,) for i in range(6)]))
    assert sorted(got) == list(range(6))
    assert {i: o.value for i, o in got.items() if o.ok} == {i: i * i for i in range(6) if i != 3}
    assert isinstance(got[3].error, ValueError) and not got[3].lost


def test_pool_resubmits_the_jobs_of_a_dead_worker(tmp_path):
    with PoolExecutor(2) as ex:
        got = dict(ex.imap_unordered(exit_once, [(i, str(tmp_path / "m")) for i in range(5)]))
        assert ex.restarts == 1
    assert {i: o.value for i, o in got.items()} == {i: i + 100 for i in range(5)}


def test_pool_that_keeps_dying_is_a_clear_error():
    with PoolExecutor(2, max_restarts=1) as ex:
        with pytest.raises(SdpError, match="died 2 times"):
            list(ex.imap_unordered(always_exit, [(0,)]))


def test_serial_executor_runs_jobs_lazily_one_by_one():
    calls = []
    ex = SerialExecutor()
    futs = [ex.submit(calls.append, i) for i in range(3)]
    assert calls == []
    assert ex.wait_any(futs) == [futs[0]] and calls == [0]


@pytest.mark.parametrize("args, message", [
    (["--executor", "ray"], "valid executors: local, dask"),
    (["--executor", "local", "--scheduler", "tcp://127.0.0.1:1"], "--scheduler needs --executor dask"),
    (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "with --scheduler the cluster's workers"),
])
def test_bad_executor_options_are_one_line_errors(tmp_path, args, message):
    r = runner.invoke(app, ["collect", "--task", "pendulum", "--out", str(tmp_path / "x.npz"), *args])
    assert r.exit_code == 1 and message in r.output and "Traceback" not in r.output
    assert not (tmp_path / "x.npz.partial").exists()


def test_failed_solve_is_a_failed_attempt_not_fatal(tmp_path, monkeypatch):
    flaky_jobs(monkeypatch)
    path, stats = collect(CollectConfig(task="pendulum", n_traj=3, seed=0), tmp_path / "f.npz", workers=2)
    arrays, _ = load_npz(path)
    assert list(arrays["index"]) == [0, 2, 3]  # index BAD converges when its job does not raise
    assert stats.rejected == 1

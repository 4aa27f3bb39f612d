"""The Dask executor: same trajectories as local, failed solves, killed client, killed worker.

The tests share one ``dask.distributed.LocalCluster`` of 2 worker processes on loopback
(started once for the module, a few seconds) and reach it through its scheduler address,
as a user with ``--scheduler tcp://HOST:PORT`` would.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import executor_jobs
from executor_jobs import BAD, assert_same_dataset, flaky_jobs
from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz, save_npz
from sdp_cli.algorithm.collect import CollectConfig, collect, sample_xi
from sdp_cli.errors import SdpError
from sdp_cli.execution.executor import make_executor
from sdp_cli.algorithm.refine import refine
from sdp_cli.tasks import get_task
from sdp_cli.trajopt import build_count

distributed = pytest.importorskip("distributed")
runner = CliRunner()


@pytest.fixture(scope="module")
def cluster():
    import cloudpickle

    cloudpickle.register_pickle_by_value(executor_jobs)  # workers cannot import the tests' files
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) as c:
        yield c
    cloudpickle.unregister_pickle_by_value(executor_jobs)


@pytest.fixture()
def dask_ex(cluster):
    with make_executor("dask", scheduler=cluster.scheduler_address) as ex:
        yield ex


def test_dask_collect_matches_local_and_builds_once_per_worker(tmp_path, dask_ex):
    cfg = CollectConfig(task="pendulum", n_traj=6, seed=1)
    local, _ = collect(cfg, tmp_path / "l.npz", workers=1)
    before = dask_ex.run_on_workers(build_count)   # the module's cluster may have built solvers already
    remote, stats = collect(cfg, tmp_path / "d.npz", executor=dask_ex)
    assert_same_dataset(local, remote)
    assert stats.attempts > 2  # more jobs than workers: the solver was reused
    after = dask_ex.run_on_workers(build_count)
    assert set(after) == set(dask_ex.client.nthreads())
    assert all(after[a] - before.get(a, 0) <= 1 for a in after)   # at most one build per worker
    _, meta = load_npz(remote)
    assert meta["config"]["executor"]["kind"] == "dask" and meta["config"]["workers"] == 2


def test_dask_failed_solve_is_recorded_and_results_match_local(tmp_path, dask_ex, monkeypatch):
    flaky_jobs(monkeypatch)
    cfg = CollectConfig(task="pendulum", n_traj=3, seed=0)
    local, _ = collect(cfg, tmp_path / "l.npz", workers=1)
    with pytest.raises(SdpError, match=r"1 raised an error, e.g. error: RuntimeError: worker-side failure"):
        collect(CollectConfig(task="pendulum", n_traj=3, seed=0, max_attempts=3), tmp_path / "x.npz",
                executor=dask_ex)
    remote, _ = collect(cfg, tmp_path / "d.npz", executor=dask_ex)
    assert BAD not in assert_same_dataset(local, remote)["index"]


def test_dask_refine_matches_local(tmp_path, dask_ex):
    task = get_task("pendulum")
    xi = np.stack([sample_xi(task, 5, i) for i in range(3)])
    X, U = map(np.stack, zip(*[task.naive_guess(x) for x in xi]))
    U = U + 0.1
    rollouts = save_npz(tmp_path / "r.npz", {"X": X, "U": U, "xi": xi}, kind="rollout", task="pendulum",
                        task_options={}, config={})
    a, _ = refine(rollouts, tmp_path / "a.npz", workers=1)
    b, _ = refine(rollouts, tmp_path / "b.npz", executor=dask_ex)
    ra, _ = load_npz(a)
    rb, _ = load_npz(b)
    np.testing.assert_array_equal(ra["inst_winner"], rb["inst_winner"])
    np.testing.assert_allclose(ra["X"], rb["X"], atol=1e-8)
    assert len(ra["X"]) >= 1


def test_worker_that_cannot_build_is_an_error_before_any_solve(dask_ex):
    with pytest.raises(SdpError, match="cannot build the solver .error: ValueError: three is not allowed"):
        dask_ex.warm(executor_jobs.square_or_raise, 3)


def test_bad_scheduler_address_is_a_clear_error():
    with pytest.raises(SdpError, match="cannot connect to the dask scheduler at tcp://127.0.0.1:9"):
        make_executor("dask", scheduler="tcp://127.0.0.1:9", connect_timeout=1)


def test_cli_collect_with_its_own_local_cluster_leaves_no_process(tmp_path):
    import psutil

    def children():   # the interpreter's multiprocessing helpers (started once, on first use) are no leak
        out = set()
        for p in psutil.Process().children(recursive=True):
            try:
                cmd = " ".join(p.cmdline())
            except psutil.Error:
                continue
            if not any(h in cmd for h in ("resource_tracker", "forkserver", "semaphore_tracker")):
                out.add(p.pid)
        return out

    before = children()
    out = tmp_path / "c.npz"
    r = runner.invoke(app, ["collect", "--task", "pendulum", "--n-traj", "3", "--seed", "0", "--out", str(out),
                            "--executor", "dask", "--workers", "2"])
    assert r.exit_code == 0, r.output
    _, meta = load_npz(out)
    assert meta["config"]["executor"]["kind"] == "dask"
    deadline = time.time() + 10
    while time.time() < deadline and children() - before:
        time.sleep(0.2)
    assert not children() - before


def test_killed_dask_client_loses_no_finished_solve(tmp_path, cluster):
    """kill -9 a `sdp collect --scheduler` client mid-run; a local re-run resumes and matches."""
    out, partial = tmp_path / "k.npz", tmp_path / "k.npz.partial"
    base = [sys.executable, "-m", "sdp_cli.cli", "collect", "--task", "pendulum", "--n-traj", "10",
            "--seed", "3", "--out", str(out)]
    proc = subprocess.Popen(base + ["--scheduler", cluster.scheduler_address], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(partial.glob("0*.npz"))) < 2 and proc.poll() is None:
        time.sleep(0.01)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    kept = {p.name: p.stat().st_mtime_ns for p in partial.glob("0*.npz")}
    assert len(kept) >= 2 and not out.exists()
    r = subprocess.run(base + ["--workers", "1"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    fresh, _ = collect(CollectConfig(task="pendulum", n_traj=10, seed=3), tmp_path / "f.npz", workers=1)
    assert_same_dataset(out, fresh)


def test_collect_completes_when_a_dask_worker_is_killed(tmp_path, cluster, dask_ex):
    """SIGKILL one of the 2 worker processes after the first results; same dataset as local."""
    cfg = CollectConfig(task="double_pendulum", n_traj=12, seed=4)
    pids = dask_ex.worker_pids()
    victim = sorted(pids.values())[0]
    killed = []

    def progress(stats):
        if stats.attempts >= 2 and not killed:
            os.kill(victim, signal.SIGKILL)
            killed.append(stats.attempts)

    remote, stats = collect(cfg, tmp_path / "d.npz", executor=dask_ex, progress=progress)
    assert killed and killed[0] < stats.attempts  # the kill happened mid-run
    local, _ = collect(cfg, tmp_path / "l.npz", workers=2)
    assert_same_dataset(local, remote)
    assert victim not in dask_ex.worker_pids().values()


def test_local_cluster_leaves_this_process_environment_alone(monkeypatch):
    """A LocalCluster's nannies write OMP_NUM_THREADS=1 (and more) into the parent's os.environ;
    a later subprocess (e.g. `dvc repro` in the regression test) would inherit it."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("SDP_ENV_PROBE", "kept")
    before = dict(os.environ)
    with make_executor("dask", workers=1) as ex:
        assert ex.slots() == 1
    assert dict(os.environ) == before


def test_runs_of_an_experiment_on_dask_equal_local(tmp_path, cluster):
    """`sdp pipeline NAME --run --scheduler ADDR`: the runs execute on the cluster's workers, packed into a stack
    as on the local pool, with the same results as in this process."""
    from sdp_cli.experiments.runner import run_group

    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "tiny.yaml").write_text(
        "groups: [{task: pendulum, methods: [dp], seeds: [1, 2], n_traj: [2], epochs: 2, horizon: 8, t_a: 4, "
        "n_test: 2, train: {batch_size: 8}}]\n")
    cols = ["run", "policy_cost_mean", "refined_cost_mean", "to_alone_cost_mean"]
    logs = {"local": [], "dask": []}
    local = run_group("tiny", tmp_path / "local", executor="local", workers=1, device="cpu", root=tmp_path,
                      log=logs["local"].append)
    remote = run_group("tiny", tmp_path / "dask", scheduler=cluster.scheduler_address, device="cpu", root=tmp_path,
                       log=logs["dask"].append)
    for lines in logs.values():
        assert any("(2 of them in 1 stacks)" in line for line in lines), lines
    pd.testing.assert_frame_equal(local.sort_values("run")[cols].reset_index(drop=True),
                                  remote.sort_values("run")[cols].reset_index(drop=True))
    assert len(set(remote.run)) == 2
    assert (tmp_path / "dask" / "pendulum-dp-n2-s1" / "summary.csv").is_file()

"""`sdp collect`: artifact content, determinism across workers, resume after kill -9, bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz, load_timing
from sdp_cli.algorithm.collect import CollectConfig, _next_indices, collect, kept_indices, sample_xi
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task

runner = CliRunner()


def _done(flags):
    return {i: {"converged": np.asarray(c)} for i, c in flags.items()}


def test_kept_indices_is_first_converged_prefix():
    done = _done({0: True, 1: False, 2: True, 4: True})
    assert kept_indices(done, 2) == [0, 2]
    assert kept_indices(done, 3) is None  # index 3 unfinished: 4 cannot be kept yet
    done[3] = {"converged": np.asarray(False)}
    assert kept_indices(done, 3) == [0, 2, 4]


def test_next_indices_fills_holes_first_and_respects_cap():
    done = _done({0: True, 2: True, 5: True})  # holes 1, 3, 4 left by a crash
    assert list(_next_indices(done, set(), n_traj=3, cap=100)) == [1, 3, 4]
    assert list(_next_indices(_done({0: False}), set(), n_traj=3, cap=2)) == [1]
    assert list(_next_indices({}, {0, 1}, n_traj=3, cap=100)) == [2]


def test_sample_xi_depends_only_on_seed_and_index():
    task = get_task("double_pendulum")
    a, b = sample_xi(task, 3, 7), sample_xi(task, 3, 7)
    assert np.array_equal(a, b)
    assert not np.allclose(sample_xi(task, 3, 8), a)
    assert not np.allclose(sample_xi(task, 4, 7), a)


def test_collect_cli_writes_a_complete_dataset(tmp_path):
    out = tmp_path / "p.npz"
    r = runner.invoke(app, ["collect", "--task", "pendulum", "--n-traj", "3", "--seed", "0",
                            "--out", str(out), "--workers", "1"])
    assert r.exit_code == 0, r.output
    arrays, meta = load_npz(out, kind="dataset")
    task = get_task("pendulum")
    N, T = 3, task.T
    shapes = {"X": (N, T + 1, task.nx), "U": (N, T, task.nu), "K": (N, T, task.nu, task.ndx),
              "A": (N, T, task.ndx, task.ndx), "B": (N, T, task.ndx, task.nu),
              "Phi": (N, T, task.ndx, task.ndx), "xi": (N, task.n_xi), "cost": (N,), "iterations": (N,),
              "converged": (N,), "index": (N,), "max_violation": (N,)}
    for k, s in shapes.items():
        assert arrays[k].shape == s, k
    assert arrays["converged"].all()
    assert list(arrays["index"]) == sorted(arrays["index"])
    for n in range(N):
        xi = arrays["xi"][n]
        assert np.allclose(xi, sample_xi(task, 0, int(arrays["index"][n])))
        assert np.allclose(arrays["X"][n, 0], task.initial_state(xi))
        assert arrays["cost"][n] == pytest.approx(task.cost(arrays["X"][n], arrays["U"][n], xi), rel=1e-6)
    assert meta["task"] == "pendulum" and meta["dims"]["T"] == T
    assert meta["config"]["seed"] == 0 and meta["config"]["n_traj"] == 3
    assert meta["provenance"]["versions"]["casadi"]
    assert "git_rev" in meta["provenance"]
    assert not (tmp_path / "p.npz.partial").exists()
    # clock readings live in the timing sidecar, never in the artifact (same seed, same bytes)
    assert not any(k.endswith("_time") for k in arrays) and "created" not in meta
    timing = load_timing(out)
    assert (tmp_path / "p.timing.json").is_file() and len(timing["solve_time"]) == N
    assert all(t > 0 for t in timing["solve_time"]) and timing["wall_time"] >= sum(timing["solve_time"])


def test_collect_same_result_for_any_number_of_workers(tmp_path):
    cfg = CollectConfig(task="pendulum", n_traj=4, seed=1)
    p1, _ = collect(cfg, tmp_path / "a.npz", workers=1)
    p2, _ = collect(cfg, tmp_path / "b.npz", workers=2)
    a, _ = load_npz(p1)
    b, _ = load_npz(p2)
    assert np.array_equal(a["index"], b["index"])
    np.testing.assert_allclose(a["X"], b["X"], atol=1e-8)
    np.testing.assert_allclose(a["K"], b["K"], atol=1e-6)


def test_collect_resumes_after_kill_9(tmp_path):
    """Kill the process once some solves are on disk; the re-run keeps them and completes."""
    out = tmp_path / "r.npz"
    partial = tmp_path / "r.npz.partial"
    cmd = [sys.executable, "-m", "sdp_cli.cli", "collect", "--task", "pendulum", "--n-traj", "8",
           "--seed", "2", "--out", str(out), "--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(partial.glob("0*.npz"))) < 2 and proc.poll() is None:
        time.sleep(0.01)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists(), "killed before the end: no final artifact may exist"
    before = {p.name: p.stat().st_mtime_ns for p in partial.glob("0*.npz")}
    assert len(before) >= 2
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    resumed, _ = load_npz(out)
    fresh_path, _ = collect(CollectConfig(task="pendulum", n_traj=8, seed=2), tmp_path / "f.npz", workers=1)
    fresh, _ = load_npz(fresh_path)
    assert np.array_equal(resumed["index"], fresh["index"])
    np.testing.assert_allclose(resumed["X"], fresh["X"], atol=1e-8)


class _Stop(Exception):
    pass


def test_resumed_collection_records_the_wall_time_of_every_run(tmp_path):
    """The dataset's wall time is summed over the runs that built it: a resumed collection goes on from the
    earlier run's elapsed time (it recorded only the time after the restart)."""
    cfg = CollectConfig(task="pendulum", n_traj=4, seed=1)
    out, partial = tmp_path / "w.npz", tmp_path / "w.npz.partial"

    def stop_after_two(stats):
        if stats.attempts >= 2:
            raise _Stop

    with pytest.raises(_Stop):
        collect(cfg, out, workers=1, progress=stop_after_two)
    assert not out.exists() and len(list(partial.glob("0*.npz"))) == 2
    first = json.loads((partial / "elapsed.json").read_text())["wall_time"]
    assert 0 < first < 600
    (partial / "elapsed.json").write_text(json.dumps({"wall_time": 1000.0}))   # a long first run
    _, stats = collect(cfg, out, workers=1)
    assert 1000.0 < stats.wall_time < 1600 and load_timing(out)["wall_time"] == pytest.approx(stats.wall_time)
    assert not partial.exists()
    bad = tmp_path / "v.npz.partial"         # an unreadable record is one clear error, before any solve
    bad.mkdir()
    (bad / "manifest.json").write_text(json.dumps(cfg.identity()))
    (bad / "elapsed.json").write_text("{not json")
    with pytest.raises(SdpError, match="bad elapsed.json"):
        collect(cfg, tmp_path / "v.npz", workers=1)
    assert not (tmp_path / "v.npz").exists()


def test_collect_refuses_corrupt_partial_file(tmp_path):
    out = tmp_path / "c.npz"
    partial = tmp_path / "c.npz.partial"
    partial.mkdir()
    (partial / "manifest.json").write_text(json.dumps(
        CollectConfig(task="pendulum", n_traj=2).identity()))
    (partial / "000000.npz").write_bytes(b"not a zip file")
    r = runner.invoke(app, ["collect", "--task", "pendulum", "--n-traj", "2", "--out", str(out),
                            "--workers", "1"])
    assert r.exit_code == 1
    assert "corrupt" in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("args, message", [
    (["--task", "nope"], "valid tasks: double_pendulum"),
    (["--task", "pendulum", "--n-traj", "0"], "n_traj must be an integer >= 1"),
    (["--task", "pendulum", "--workers", "0"], "--workers must be > 0"),
    (["--task", "pendulum", "--out", "/proc/forbidden/x.npz"], "cannot write"),
])
def test_collect_bad_input_is_one_line_and_exit_1(args, message):
    r = runner.invoke(app, ["collect", *args])
    assert r.exit_code == 1
    assert message in r.output
    assert "Traceback" not in r.output


def test_collect_attempt_cap_gives_a_clear_error(tmp_path):
    with pytest.raises(SdpError, match="converged after 3 attempts"):
        collect(CollectConfig(task="pendulum", n_traj=2, max_iter=1, max_attempts=3),
                tmp_path / "x.npz", workers=1)
    # the failed solves are kept for a later run with a larger cap
    assert len(list((tmp_path / "x.npz.partial").glob("0*.npz"))) == 3

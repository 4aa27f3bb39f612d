"""No orphans, no races: a killed `sdp pipeline --run` (or the `dvc repro` that started it) takes its workers
and their children along, and a second runner on the same run folders refuses with one line.

At 38d2c04 a kill -9 of `dvc repro` left the runner and its workers training (5 processes), and the re-run
trained the same runs twice at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sdp_cli.errors import SdpError
from sdp_cli.experiments.runner import lock_path, run_group, runner_lock

LONG = """
groups:
  - task: pendulum
    methods: [dp]
    seeds: [0, 1]
    n_traj: [2]
    epochs: 100000
    horizon: 8
    t_a: 4
    n_test: 2
    train: {batch_size: 8}
"""


@pytest.fixture()
def root(tmp_path):
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "long.yaml").write_text(LONG)
    return tmp_path


def _procs_with(marker: str) -> list[int]:
    """Pids whose command line mentions ``marker`` (the runs folder: unique to this test)."""
    pids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if marker in (p / "cmdline").read_bytes().decode(errors="ignore"):
                    pids.append(int(p.name))
            except OSError:
                pass
    return pids


def _descendants(pid: int) -> set[int]:
    kids = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                ppid = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, set()).add(int(p.name))
    out, todo = set(), [pid]
    while todo:
        for k in kids.get(todo.pop(), ()):
            if k not in out:
                out.add(k)
                todo.append(k)
    return out


def _wait_for(cond, timeout=60.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return True
        time.sleep(0.2)
    return False


def _sdp(*args):
    return [sys.executable, "-c", "from sdp_cli.cli import app; app()", *args]


def test_a_second_runner_on_the_same_folder_refuses_with_the_owner(root, tmp_path):
    out = tmp_path / "runs" / "long"
    with runner_lock(out):
        with pytest.raises(SdpError, match=f"being run by another .* \\(pid {os.getpid()}\\)"):
            run_group("long", out, workers=1, root=root, log=lambda s: None)
    assert lock_path(out) == tmp_path / "runs" / ".long.lock" and not out.exists()
    with runner_lock(out):     # released: the lock can be taken again
        pass


@pytest.mark.parametrize("under_dvc", [False, True])
def test_kill_9_takes_workers_and_their_children_along(root, tmp_path, under_dvc):
    """kill -9 of the runner, or of the parent that started it under DVC (DVC_STAGE set), leaves no process;
    while it lives a second runner refuses with one line."""
    out = tmp_path / "runs" / "long"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = _sdp("pipeline", "long", "--run", "--workers", "2", "--out", str(out))
    if under_dvc:   # a stand-in for dvc: a parent that runs the stage command and waits
        env["DVC_STAGE"] = "group@long"
        cmd = [sys.executable, "-c", "import subprocess, sys; subprocess.run(sys.argv[1:])", *cmd]
    top = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert _wait_for(lambda: len(_descendants(top.pid)) >= (3 if under_dvc else 2)), "workers never started"
        assert _wait_for(lambda: any((out / r / "it0" / "policy").is_dir() for r in ("pendulum-dp-n2-s0",
                                                                                    "pendulum-dp-n2-s1")))
        r = subprocess.run(_sdp("pipeline", "long", "--run", "--workers", "1", "--out", str(out)), cwd=root,
                           env=env, capture_output=True, text=True)
        assert r.returncode == 1 and "being run by another" in r.stderr and len(r.stderr.strip().splitlines()) == 1
        family = _descendants(top.pid)
        os.kill(top.pid, signal.SIGKILL)
        top.wait()
        assert _wait_for(lambda: not [p for p in family if Path(f"/proc/{p}").exists()
                                      and "Z" not in (Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1][:3])],
                         timeout=20), f"left behind: {_procs_with(str(out))}"
    finally:
        for p in _procs_with(str(out)):
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass


MID = LONG.replace("epochs: 100000", "epochs: 600").replace("train: {batch_size: 8}",
                                                             "train: {batch_size: 8, down_dims: [8, 16], n_groups: 4}")


def test_ctrl_c_of_the_parallel_runner_then_the_same_command_gives_the_same_results(root, tmp_path):
    """Ctrl-C (SIGINT to the runner's process group, as a terminal sends it) while both runs train, then the
    same command: every run's evaluation and training curve equal an uninterrupted runner's."""
    import pandas as pd

    (root / "pipelines" / "mid.yaml").write_text(MID)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ref, out = tmp_path / "runs" / "ref", tmp_path / "runs" / "mid"
    subprocess.run(_sdp("pipeline", "mid", "--run", "--workers", "2", "--stack", "1", "--out", str(ref)), cwd=root, env=env,
                   check=True, capture_output=True)
    p = subprocess.Popen(_sdp("pipeline", "mid", "--run", "--workers", "2", "--stack", "1", "--out", str(out)), cwd=root, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
                         # as from a terminal, even when this suite runs in the background (SIGINT ignored)
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    runs = ("pendulum-dp-n2-s0", "pendulum-dp-n2-s1")
    assert _wait_for(lambda: all((out / r / "it0" / "policy" / "metrics.csv").exists() for r in runs), timeout=120)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130 and "Traceback" not in err.decode(), err.decode()[-2000:]
    assert _wait_for(lambda: not _procs_with(str(out)), timeout=20)
    from sdp_cli.policy.checkpoint import load_checkpoint

    assert not all(load_checkpoint(out / r / "it0" / "policy")["finished"] for r in runs)   # stopped mid-training
    r = subprocess.run(_sdp("pipeline", "mid", "--run", "--workers", "2", "--stack", "1", "--out", str(out)), cwd=root, env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    for run in runs:
        a, b = (pd.read_csv(d / run / "summary.csv") for d in (ref, out))
        pd.testing.assert_frame_equal(a, b)
        for f in ("metrics.csv", "checkpoint.pt"):
            assert (ref / run / "it0" / "policy" / f).read_bytes() == (out / run / "it0" / "policy" / f).read_bytes()

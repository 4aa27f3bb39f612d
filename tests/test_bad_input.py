"""Bad input: one line on stderr, exit code 1, no traceback, and nothing half-written.

Each case was seen at commit d8ae24d as a traceback, a leftover file or a silent mistake.
(Tests run as root, where permission bits do not block writes: unwritable places are paths
under an existing *file*, which no user can create.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.collect import CollectConfig, collect
from sdp_cli.policy.config import TrainConfig
from sdp_cli.train import train
from synthetic_dataset import one_torch_thread, write_dataset  # noqa: F401 (autouse fixture)

runner = CliRunner()
TINY = {"down_dims": [8, 16], "step_embed_dim": 16, "n_groups": 4, "batch_size": 32, "T_h": 8}


def _fails_cleanly(r, *needles):
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    for n in needles:
        assert n in r.output, r.output


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A pendulum dataset, a tiny DP policy, its rollouts and their refinement."""
    root = tmp_path_factory.mktemp("bad")
    data, _ = collect(CollectConfig(task="pendulum", n_traj=2, seed=0), root / "data.npz", workers=1)
    cfg = TrainConfig.from_dict({**TrainConfig().to_dict(), **TINY, "method": "dp", "epochs": 2})
    train(data, root / "pol", cfg, device="cpu", progress=False, log=lambda s: None)
    out = {"data": data, "pol": root / "pol", "file": root / "a_file"}
    out["file"].write_text("x")
    for k in ("a", "b"):
        r = runner.invoke(app, ["rollout", "--policy", str(root / "pol"), "--n", "2", "--seed", str(len(k) + (k == "b")),
                                "--out", str(root / f"r{k}.npz")])
        assert r.exit_code == 0, r.output
        out[f"r{k}"] = root / f"r{k}.npz"
    r = runner.invoke(app, ["refine", "--rollouts", str(out["ra"]), "--out", str(root / "fa.npz"), "--workers", "1"])
    assert r.exit_code == 0, r.output
    out["fa"] = root / "fa.npz"
    return out


def test_train_unwritable_out_and_bad_numbers(run, tmp_path):
    r = runner.invoke(app, ["train", "--data", str(run["data"]), "--method", "dp", "--epochs", "1", "--horizon", "8",
                            "--out", str(run["file"] / "sub")])
    _fails_cleanly(r, "cannot create the run folder")
    for opt, val, msg in (("--lr", "-1", "lr must be"), ("--lr", "nan", "lr must be"),
                          ("--batch-size", "0", "batch_size must be"), ("--alpha-sobolev", "-2", "alpha_sobolev")):
        r = runner.invoke(app, ["train", "--data", str(run["data"]), "--method", "sdp", "--epochs", "1",
                                "--horizon", "8", opt, val, "--out", str(tmp_path / "x")])
        _fails_cleanly(r, msg)
        assert not (tmp_path / "x").exists()


def test_train_resume_with_other_epochs_is_refused(run, tmp_path):
    args = ["train", "--data", str(run["data"]), "--method", "dp", "--epochs", "1", "--horizon", "8",
            "--down-dims", "8,16", "--out", str(tmp_path / "r"), "--no-progress"]
    assert runner.invoke(app, args).exit_code == 0
    r = runner.invoke(app, [a if a != "1" else "5" for a in args] + ["--resume"])
    _fails_cleanly(r, "cannot resume", "epochs=5", "run: 1")
    assert runner.invoke(app, args + ["--resume"]).exit_code == 0      # the same options resume


@pytest.mark.parametrize("args,msg", [
    (["--task", "nope", "--method", "sdp"], "unknown task"),
    (["--task", "pendulum", "--method", "foo"], "method must be one of"),
    (["--task", "pendulum", "--method", "sdp", "--horizon", "12"], "divisible"),
    (["--task", "pendulum", "--method", "sdp", "--horizon", "16", "--t-a", "40"], "t_a [40] outside"),
])
def test_loop_validates_everything_before_writing(tmp_path, args, msg):
    r = runner.invoke(app, ["loop", *args, "--out", str(tmp_path / "loop")])
    _fails_cleanly(r, msg)
    assert not (tmp_path / "loop").exists()


def test_loop_unwritable_out(run):
    _fails_cleanly(runner.invoke(app, ["loop", "--task", "pendulum", "--method", "dp", "--out", str(run["file"] / "x")]),
                   "cannot create the loop folder")


@pytest.mark.parametrize("extra,msg", [(["--t-a", "99"], "t_a must be in"), (["--task", "double_pendulum"], "trained on task")])
def test_failed_collect_leaves_no_partial_folder(run, tmp_path, extra, msg):
    out = tmp_path / "d.npz"
    args = ["collect", "--task", "pendulum", "--n-traj", "2", "--policy", str(run["pol"]), "--out", str(out), *extra]
    if "--task" in extra:
        args = ["collect", "--n-traj", "2", "--policy", str(run["pol"]), "--out", str(out), *extra]
    _fails_cleanly(runner.invoke(app, args), msg)
    assert list(tmp_path.iterdir()) == []


def test_collect_unreachable_scheduler_leaves_no_partial_folder(tmp_path):
    out = tmp_path / "d.npz"
    r = runner.invoke(app, ["collect", "--task", "pendulum", "--n-traj", "2", "--out", str(out),
                            "--scheduler", "tcp://127.0.0.1:1"])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert list(tmp_path.iterdir()) == []


def test_evaluate_checks_both_outputs_and_pairing(run, tmp_path):
    ok = tmp_path / "ok.csv"
    r = runner.invoke(app, ["evaluate", "--rollouts", str(run["ra"]), "--refined", str(run["fa"]), "--out", str(ok),
                            "--metrics", str(run["file"] / "m.json")])
    _fails_cleanly(r, "cannot write")
    assert not ok.exists()
    r = runner.invoke(app, ["evaluate", "--rollouts", str(run["rb"]), "--refined", str(run["fa"]), "--out", str(ok)])
    _fails_cleanly(r, "refines another rollout artifact")
    assert not ok.exists()
    r = runner.invoke(app, ["evaluate", "--rollouts", str(run["ra"]), "--refined", str(run["fa"]), "--out", str(ok)])
    assert r.exit_code == 0 and pd.read_csv(ok).n.iloc[0] == 2


def test_corrupt_inputs_never_advise_unsafe_loading(run, tmp_path):
    pickled = tmp_path / "p.npz"
    np.savez(pickled, X=np.array([{"a": 1}], dtype=object), __meta__=np.array('{"kind": "rollout"}'))
    r = runner.invoke(app, ["refine", "--rollouts", str(pickled), "--out", str(tmp_path / "o.npz")])
    _fails_cleanly(r, "corrupt artifact")
    assert "allow_pickle" not in r.output
    ck = tmp_path / "bad.pt"
    import torch

    torch.save({"x": _Unsafe()}, ck)   # loadable only unsafely
    r = runner.invoke(app, ["rollout", "--policy", str(ck), "--out", str(tmp_path / "r.npz")])
    _fails_cleanly(r, "corrupt checkpoint")
    assert "weights_only" not in r.output
    junk = tmp_path / "junk.npz"
    np.savez(junk, __meta__=np.array('{"kind": "rollout", "config": {}}'))
    r = runner.invoke(app, ["evaluate", "--rollouts", str(junk), "--out", str(tmp_path / "e.csv")])
    _fails_cleanly(r, "corrupt rollout artifact")
    r = runner.invoke(app, ["refine", "--rollouts", str(junk), "--out", str(tmp_path / "o.npz")])
    _fails_cleanly(r)


class _Unsafe:
    """An arbitrary class: torch.load(weights_only=True) refuses it and suggests weights_only=False."""


def _children(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [int(p) for p in out]


def test_kill_9_of_collect_takes_its_workers_along(tmp_path):
    env = {**os.environ, "SDP_NO_PROGRESS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sdp_cli.cli", "collect", "--task", "double_pendulum", "--n-traj",
                             "400", "--workers", "2", "--out", str(tmp_path / "d.npz")], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        kids = []
        while time.time() < deadline and len(kids) < 2:
            time.sleep(0.2)
            kids = _children(proc.pid)
        assert len(kids) >= 2, "the pool workers did not start"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 10
        while time.time() < deadline and any(Path(f"/proc/{k}").exists() for k in kids):
            time.sleep(0.2)
        alive = [k for k in kids if Path(f"/proc/{k}").exists() and "Z" not in Path(f"/proc/{k}/stat").read_text().split()[2]]
        assert not alive, f"orphaned workers {alive}"
    finally:
        if proc.poll() is None:
            proc.kill()

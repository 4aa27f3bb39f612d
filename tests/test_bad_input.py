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
from sdp_cli.algorithm.collect import CollectConfig, collect
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train

runner = CliRunner()
TINY = {"down_dims": [8, 16], "step_embed_dim": 16, "n_groups": 4, "batch_size": 32, "horizon": 8}


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
    cfg = TrainConfig.of(**{**TINY, "method": "dp", "epochs": 2})
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
                          ("--batch-size", "0", "batch_size must be"), ("--sobolev-alpha", "-2", "sobolev_alpha")):
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


@pytest.mark.parametrize("seed", ["-1", "1000000"])
@pytest.mark.parametrize("cmd", ["collect", "train", "loop", "rollout", "loop-test-seed"])
def test_one_rule_for_seeds_before_anything_is_written(run, tmp_path, cmd, seed):
    """Seeds are integers in [0, 1e6) (test instances come from 1e6 + seed; a loop's collections from
    1000 seed + k, so its seed is below 1000) in every command, checked before any file is written
    (at d8ae24d a negative seed was a numpy traceback in collect, loop and rollout, accepted by train,
    and loop left its folder behind)."""
    out = tmp_path / "out"
    args = {"collect": ["collect", "--task", "pendulum", "--n-traj", "1", "--seed", seed, "--out", str(out / "d.npz")],
            "train": ["train", "--data", str(run["data"]), "--method", "dp", "--epochs", "1", "--horizon", "8",
                      "--seed", seed, "--out", str(out)],
            "loop": ["loop", "--task", "pendulum", "--method", "dp", "--seed", seed, "--out", str(out)],
            "loop-test-seed": ["loop", "--task", "pendulum", "--method", "dp", "--test-seed", seed, "--out", str(out)],
            "rollout": ["rollout", "--policy", str(run["pol"]), "--n", "1", "--seed", seed, "--out", str(out / "r.npz")],
            }[cmd]
    _fails_cleanly(runner.invoke(app, args), "seed must be an integer in [0, ")
    assert not out.exists()
    if cmd == "loop":
        _fails_cleanly(runner.invoke(app, args[:-4] + ["--seed", "1000", "--out", str(out)]), "[0, 999]")


def test_train_save_at_beyond_epochs_is_refused(run, tmp_path):
    """`sdp train --save-at 5 --epochs 2` succeeded silently at 38d2c04 while `sdp loop` refused it."""
    for save in ("5", "2", "0"):
        r = runner.invoke(app, ["train", "--data", str(run["data"]), "--method", "dp", "--epochs", "2", "--horizon",
                                "8", "--save-at", save, "--out", str(tmp_path / "x")])
        _fails_cleanly(r, "save_at epochs must be in (0, epochs = 2)")
        assert not (tmp_path / "x").exists()
    r = runner.invoke(app, ["loop", "--task", "pendulum", "--method", "dp", "--epochs", "2", "--save-at", "5",
                            "--out", str(tmp_path / "x")])
    _fails_cleanly(r, "save_at epochs must be in (0, epochs = 2)")


GOOD_GROUP = {"task": "pendulum", "methods": ["dp"], "seeds": [0], "n_traj": [2], "epochs": 2, "horizon": 8, "t_a": 4}


@pytest.mark.parametrize("key,value,msg", [
    ("seeds", 3, "key 'seeds': must be a list of integers"),
    ("n_traj", 5, "key 'n_traj': must be a list of integers"),
    ("epochs", "many", "key 'epochs': must be an integer"),
    ("save_at", 5, "key 'save_at': must be a list of integers"),
    ("methods", "dp", "key 'methods': must be a list of strings"),
    ("single_shooting", "yes", "key 'single_shooting': must be true or false"),
    ("t_a", 2.5, "key 't_a': must be an integer (or null)"),
    ("seeds", [-1], "seed must be an integer in [0, 999]"),
    ("train", {"batch_size": "big"}, "key 'train.batch_size': must be an integer"),
    ("train", {"lr": "fast"}, "key 'train.lr': must be a number"),
])
@pytest.mark.parametrize("mode", ["--estimate", "--run", "select"])
def test_mistyped_experiment_files_name_file_group_and_key(tmp_path, monkeypatch, key, value, msg, mode):
    """At 38d2c04 each of these was a traceback from `sdp pipeline NAME --estimate` / `--run`."""
    import yaml

    (tmp_path / "pipelines").mkdir()
    groups = [GOOD_GROUP, {**GOOD_GROUP, "tag": "b", key: value}]
    (tmp_path / "pipelines" / "bad.yaml").write_text(yaml.safe_dump({"groups": groups}))
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["pipeline", "bad"] + ([mode] if mode != "select" else []))
    _fails_cleanly(r, "pipelines/bad.yaml, group 1", msg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipelines"]


def test_task_options_survive_policy_rollout_and_refine(tmp_path):
    """A task built with options (pendulum, T = 24): the policy keeps them, its rollouts record them and
    `sdp refine` accepts the rollouts (at 38d2c04 the policy dropped them and refine refused its own
    rollouts: 'task parameters differ')."""
    from sdp_cli.data.artifacts import load_npz
    from sdp_cli.policy import load_policy

    data, _ = collect(CollectConfig(task="pendulum", n_traj=2, seed=0, task_options={"T": 24}), tmp_path / "d.npz",
                      workers=1)
    cfg = TrainConfig.of(**{**TINY, "method": "dp", "epochs": 1})
    train(data, tmp_path / "pol", cfg, device="cpu", progress=False, log=lambda s: None)
    pol = load_policy(tmp_path / "pol")
    assert pol.task_options == {"T": 24} and pol.task.T == 24
    r = runner.invoke(app, ["rollout", "--policy", str(tmp_path / "pol"), "--n", "2", "--out", str(tmp_path / "r.npz")])
    assert r.exit_code == 0, r.output
    _, meta = load_npz(tmp_path / "r.npz", kind="rollout")
    assert meta["task_options"] == {"T": 24}
    r = runner.invoke(app, ["refine", "--rollouts", str(tmp_path / "r.npz"), "--out", str(tmp_path / "f.npz"),
                            "--workers", "1", "--no-baseline"])
    assert r.exit_code == 0, r.output
    arrays, meta = load_npz(tmp_path / "f.npz", kind="dataset")
    assert meta["task_options"] == {"T": 24} and arrays["U"].shape[1] == 24


@pytest.mark.parametrize("argv,msg", [(["loop", "--nope"], "No such option: --nope"),
                                      (["loop", "--task", "pendulum", "--method", "dp", "--seed", "abc"], "'--seed'"),
                                      (["train"], "Missing option '--data'")])
def test_usage_errors_are_one_line_with_exit_code_2(capsys, argv, msg):
    """At 38d2c04 a usage error printed a 5-6 line box; the README says: one line, exit code 2 (click's)."""
    from sdp_cli.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and msg in err and "--help" in err, err


@pytest.mark.parametrize("cmd", ["train", "loop", "refine", "pipeline", "report"])
def test_help_shows_no_type_after_flags(cmd):
    """`--resume <bool>`, `--progress/--no-progress <bool>` at 38d2c04."""
    r = runner.invoke(app, [cmd, "--help"])
    assert r.exit_code == 0 and "<bool>" not in r.output


def test_outputs_are_checked_before_the_work(run, tmp_path):
    """At 38d2c04 `rollout` and `refine` found an unwritable --out only after all their work (32 s, 67 s);
    `train --lr 1e30` left an empty run folder; `sdp report` without --out wrote into results/."""
    import time as _time

    t0 = _time.perf_counter()
    _fails_cleanly(runner.invoke(app, ["rollout", "--policy", str(run["pol"]), "--n", "50", "--out",
                                       str(run["file"] / "r.npz")]), "cannot write")
    _fails_cleanly(runner.invoke(app, ["refine", "--rollouts", str(run["ra"]), "--workers", "1", "--out",
                                       str(run["file"] / "f.npz")]), "cannot write")
    assert _time.perf_counter() - t0 < 5
    r = runner.invoke(app, ["train", "--data", str(run["data"]), "--method", "dp", "--epochs", "20", "--horizon",
                            "8", "--lr", "1e30", "--out", str(tmp_path / "diverged")])
    assert r.exit_code == 1 and "Error: training diverged" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "diverged").exists()
    _fails_cleanly(runner.invoke(app, ["report", "--runs", str(tmp_path)]), "--runs needs --out")

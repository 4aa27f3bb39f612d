"""Every bad input, one line and nothing harmed (issue 76): one table test per class of what was left at
3cd1b8b. Each case asserts the exit code, a single stderr line naming the option or path, no traceback, and that
nothing was created or changed outside what the command may write (a snapshot of the folder before and after).

Classes: 1 outputs that are not regular files, 2 options out of range or not finite, 3 OS errors at write time,
4 commands without the error handler, 5 options silently ignored, 6 malformed metadata, 7 leftovers (the runner's
lock), 8 timing files of another artifact.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.algorithm.collect import CollectConfig, collect
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()
TINY = {"down_dims": [8, 16], "step_embed_dim": 16, "n_groups": 4, "batch_size": 32, "horizon": 8}
TINY_FLAGS = ["--down-dims", "8,16", "--step-embed-dim", "16", "--n-groups", "4", "--batch-size", "32",
              "--horizon", "8", "--epochs", "1", "--no-progress"]


def snapshot(root: Path) -> dict:
    """``{relative path: (file type, sha256 of a regular file's bytes)}`` of everything under ``root``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            mode = p.lstat().st_mode
            digest = hashlib.sha256(p.read_bytes()).hexdigest() if stat.S_ISREG(mode) else None
            out[str(p.relative_to(root))] = (stat.S_IFMT(mode), digest)
    return out


def one_line(r, code: int, *needles: str) -> None:
    """Exit code ``code``, one line on stderr holding every needle, no traceback anywhere."""
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and len(r.stderr.strip().splitlines()) == 1, r.output
    for n in needles:
        assert n in r.stderr, r.stderr


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Artifacts of a tiny pendulum run (read-only inputs of every case): dataset, DP policy, rollouts,
    refinement, evaluation."""
    root = tmp_path_factory.mktemp("made")
    data, _ = collect(CollectConfig(task="pendulum", n_traj=2, seed=0), root / "data.npz", workers=1)
    train(data, root / "pol", TrainConfig.of(**{**TINY, "method": "dp", "epochs": 1}), device="cpu", progress=False,
          log=lambda s: None)
    for args in (["rollout", "--policy", str(root / "pol"), "--n", "2", "--out", str(root / "r.npz")],
                 ["refine", "--rollouts", str(root / "r.npz"), "--out", str(root / "f.npz"), "--workers", "1",
                  "--no-baseline"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, r.output
    return {"data": root / "data.npz", "pol": root / "pol", "r": root / "r.npz", "f": root / "f.npz"}


@pytest.fixture()
def work(tmp_path, monkeypatch):
    """A folder to run in (the cwd), holding a fifo, a plain file, a folder and the `small` experiment file."""
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    (tmp_path / "pipelines").mkdir()
    shutil.copy(ROOT / "pipelines" / "small.yaml", tmp_path / "pipelines" / "small.yaml")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _args(made: dict, argv: list[str]) -> list[str]:
    return [str(made[a[1:-1]]) if a.startswith("{") and a.endswith("}") else a for a in argv]


def _unchanged(work: Path, argv: list[str], made: dict, code: int, *needles: str) -> None:
    before = snapshot(work)
    one_line(runner.invoke(app, _args(made, argv)), code, *needles)
    assert snapshot(work) == before


# ----------------------------------------------------------------------------- 1. outputs not regular files
@pytest.mark.parametrize("argv,needle", [
    (["collect", "--task", "pendulum", "--n-traj", "1", "--workers", "1", "--out", "fifo"], "fifo"),
    (["rollout", "--policy", "{pol}", "--n", "1", "--out", "fifo"], "fifo"),
    (["refine", "--rollouts", "{r}", "--workers", "1", "--out", "fifo"], "fifo"),
    (["evaluate", "--rollouts", "{r}", "--out", "fifo"], "fifo"),
    (["evaluate", "--rollouts", "{r}", "--out", "e.csv", "--metrics", "fifo"], "fifo"),
    (["report", "--runs", ".", "--out", "rep", "--metrics", "fifo"], "fifo"),
    (["report", "--ledger", "fifo"], "fifo"),
    (["pipeline", "small", "--params", "adir"], "adir"),
])
def test_outputs_that_are_not_regular_files_are_refused_before_work(made, work, argv, needle):
    """At 3cd1b8b `--out /dev/full` replaced the device node by a regular file and wrote its sidecars into /dev."""
    _unchanged(work, argv, made, 1, needle)
    assert stat.S_ISFIFO((work / "fifo").stat().st_mode)


# ----------------------------------------------------------------------------- 2. range and finiteness
@pytest.mark.parametrize("argv,needle", [
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--ema-power", "nan", "--out", "p"], "ema_power"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--ema-power", "-1", "--out", "p"], "ema_power"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--step-embed-dim", "0", "--out", "p"],
     "step_embed_dim"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--n-groups", "0", "--out", "p"], "n_groups"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--n-groups", "-8", "--out", "p"], "n_groups"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--kernel-size", "0", "--out", "p"], "kernel_size"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--kernel-size", "4", "--out", "p"], "kernel_size"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--ema-power", "inf", "--out", "p"], "ema_power"),
    (["loop", "--task", "pendulum", "--method", "dp", "--kernel-size", "2", "--out", "L"], "kernel_size"),
    (["plot-dataset", "{data}", "--out", "x.png", "--dpi", "0"], "--dpi"),
    (["plot-dataset", "{data}", "--out", "x.png", "--dpi", "100000"], "--dpi"),
    (["pipeline", "small", "--estimate", "--stack", "0"], "--stack"),
])
def test_numeric_options_are_finite_and_in_range(made, work, argv, needle):
    """At 3cd1b8b `--ema-power nan` trained a policy whose EMA weights were NaN (exit 0), `--n-groups 0`,
    `--kernel-size 4`, `--dpi 0` ended in tracebacks and an empty run folder."""
    _unchanged(work, argv, made, 1, needle)


@pytest.mark.parametrize("key,value,needle", [
    ("train", {"ema_power": float("nan")}, "ema_power"),
    ("train", {"kernel_size": 4}, "kernel_size"),
    ("train", {"n_groups": -8}, "n_groups"),
    ("train", {"step_embed_dim": 0}, "step_embed_dim"),
    ("train", {"ema_power": -1.0}, "ema_power"),
])
def test_experiment_file_keys_obey_the_same_rules(made, work, key, value, needle):
    spec = yaml.safe_load((work / "pipelines" / "small.yaml").read_text())
    spec["groups"]["pendulum-sdp-dp"][key] = value
    (work / "pipelines" / "small.yaml").write_text(yaml.safe_dump(spec))
    _unchanged(work, ["pipeline", "small", "--estimate"], made, 1, "pipelines/small.yaml, group pendulum-sdp-dp",
               needle)


def test_a_policy_with_non_finite_weights_is_refused_at_load(made, work):
    """At 3cd1b8b the rollout of such a policy exited 0 with every rollout diverged, reported as a result."""
    import torch

    ck = torch.load(made["pol"] / "checkpoint.pt", weights_only=True)
    first = next(k for k, v in ck["ema_model"].items() if v.is_floating_point())
    ck["ema_model"][first] = torch.full_like(ck["ema_model"][first], float("nan"))
    torch.save(ck, work / "nan.pt")
    _unchanged(work, ["rollout", "--policy", "nan.pt", "--n", "1", "--out", "r.npz"], made, 1, "not finite", "nan.pt")


# ----------------------------------------------------------------------------- 3. OS errors at write time
@pytest.fixture()
def full_disk_at(monkeypatch):
    """``full_disk_at(n)``: the n-th write of an sdp artifact file fails with ENOSPC after its bytes reached the
    file (at its fsync); the writes before it succeed."""
    real = os.fsync

    def arm(n: int):
        calls = {"n": 0}

        def fsync(fd):
            name = os.readlink(f"/proc/self/fd/{fd}")
            if Path(name).name.startswith(".") and name.endswith(".tmp"):   # atomic_write_bytes' temp files
                calls["n"] += 1
                if calls["n"] == n:
                    raise OSError(errno.ENOSPC, "No space left on device")
            return real(fd)

        monkeypatch.setattr(os, "fsync", fsync)
        return calls
    return arm


@pytest.mark.parametrize("argv,n_writes", [
    (["collect", "--task", "pendulum", "--n-traj", "2", "--workers", "1", "--out", "d.npz"], 2),   # manifest, solve
    (["collect", "--task", "pendulum", "--n-traj", "2", "--workers", "1", "--out", "d.npz"], 3),   # its sidecar
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--out", "p"], 2),   # metrics, checkpoint
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--out", "p"], 3),   # timing
    (["rollout", "--policy", "{pol}", "--n", "1", "--out", "r.npz"], 2),                # the .npz, its sidecar
    (["rollout", "--policy", "{pol}", "--n", "1", "--out", "old.npz"], 2),              # over an earlier artifact
    (["evaluate", "--rollouts", "{r}", "--out", "e.csv"], 2),                           # csv, sidecar, manifest
    (["evaluate", "--rollouts", "{r}", "--out", "e.csv"], 3),
    (["evaluate", "--rollouts", "{r}", "--out", "e.csv", "--metrics", "m.json"], 4),
])
def test_a_full_disk_leaves_no_part_of_the_artifact(made, work, full_disk_at, argv, n_writes):
    """At 3cd1b8b an ENOSPC was an OSError traceback and the artifact's first file stayed (the .npz without
    its sidecar, collect's manifest without a solve)."""
    shutil.copy(made["r"], work / "old.npz")   # an earlier artifact at the output path must come back unchanged
    shutil.copy(made["r"].with_name("r.timing.json"), work / "old.timing.json")
    calls = full_disk_at(n_writes)
    _unchanged(work, argv, made, 1, "No space left on device")
    assert calls["n"] == n_writes


# ----------------------------------------------------------------------------- 4. every command's errors
@pytest.mark.parametrize("argv,needle", [
    (["migrate", "nope"], "nope"),
    (["migrate", "afile"], "afile"),
    (["report", "--runs", ".", "--out", "afile/res"], "afile"),
    (["pipeline", "small", "--run", "--out", "afile/R"], "afile"),
])
def test_every_command_turns_its_errors_into_one_line(made, work, argv, needle):
    """At 3cd1b8b each of these printed a traceback (`sdp migrate` had no error handler; the others an
    uncaught FileExistsError)."""
    _unchanged(work, argv, made, 1, needle)


def test_ctrl_c_during_start_up_is_one_line(tmp_path):
    """A KeyboardInterrupt while the CLI's modules import (seconds: torch, casadi, pinocchio) is "Interrupted."
    and exit code 130, as it is later. The entry point `sdp` installs (pyproject's script) is imported under an
    import hook that interrupts the import of typer (at 3cd1b8b, sdp_cli.cli:main: a traceback)."""
    target = next(line.split("=", 1)[1].strip().strip('"') for line in (ROOT / "pyproject.toml").read_text().splitlines()
                  if line.startswith("sdp ="))
    module, func = target.split(":")
    code = ("import sys\n"
            "class Interrupt:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'typer':\n"
            "            raise KeyboardInterrupt\n"
            "sys.meta_path.insert(0, Interrupt())\n"
            f"from {module} import {func} as main\n"
            "sys.exit(main(['tasks']))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 130 and r.stderr.strip() == "Interrupted." and "Traceback" not in r.stderr, r.stderr


# ----------------------------------------------------------------------------- 5. options silently ignored
@pytest.mark.parametrize("argv,code,needle", [
    (["collect", "--task", "pendulum", "--n-traj", "1", "--t-a", "4", "--out", "d.npz"], 1, "--policy"),
    (["collect", "--task", "pendulum", "--n-traj", "1", "--k-rollout", "2", "--out", "d.npz"], 1, "--policy"),
    (["train", "--data", "{data}", "--method", "dp", *TINY_FLAGS, "--resume", "--out", "adir"], 1, "--resume"),
    (["check-task", "pendulum", "--no-solve", "--cases", "8:4"], 1, "--cases"),
])
def test_options_that_would_be_ignored_are_refused(made, work, argv, code, needle):
    """At 3cd1b8b `collect --t-a` without `--policy` ignored it, `train --resume` on an empty folder started a
    new run without a word."""
    _unchanged(work, argv, made, code, needle)


@pytest.mark.parametrize("key", ["methods", "n_traj", "seeds"])
@pytest.mark.parametrize("mode", ["--estimate", "--run", "select"])
def test_an_empty_sweep_is_refused(made, work, key, mode):
    """At 3cd1b8b `methods: []` selected an experiment of 0 runs with exit code 0."""
    spec = yaml.safe_load((work / "pipelines" / "small.yaml").read_text())
    spec["groups"]["pendulum-sdp-dp"][key] = []
    (work / "pipelines" / "small.yaml").write_text(yaml.safe_dump(spec))
    _unchanged(work, ["pipeline", "small"] + ([mode] if mode != "select" else []), made, 1,
               f"group pendulum-sdp-dp, key {key!r}")


def test_init_says_which_asked_for_settings_its_architecture_replaces(made, work):
    """At 3cd1b8b `--init` with another `--down-dims` trained the init's architecture without a word."""
    r = runner.invoke(app, ["train", "--data", str(made["data"]), "--method", "dp", "--init", str(made["pol"]),
                            *TINY_FLAGS, "--down-dims", "16,32", "--out", "p"])
    assert r.exit_code == 0, r.output
    assert "--init's architecture replaces down_dims [16, 32] by [8, 16]" in r.output
    r = runner.invoke(app, ["train", "--data", str(made["data"]), "--method", "dp", "--init", str(made["pol"]),
                            *TINY_FLAGS, "--out", "p2"])
    assert r.exit_code == 0 and "replaces" not in r.output       # nothing replaced, nothing said


# ----------------------------------------------------------------------------- 6. malformed metadata
@pytest.mark.parametrize("field,value", [("format_version", "abc"), ("kind", 5), ("config", "x"), ("task", 3),
                                         ("task_options", [1]), ("dims", None)])
@pytest.mark.parametrize("cmd", ["train", "plot-dataset", "refine"])
def test_metadata_fields_are_type_checked_on_load(made, work, field, value, cmd):
    """At 3cd1b8b `"format_version": "abc"` was a TypeError traceback."""
    src = made["r"] if cmd == "refine" else made["data"]
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["__meta__"]))
    meta[field] = value
    arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(work / "bad.npz", **arrays)
    argv = {"train": ["train", "--data", "bad.npz", "--method", "dp", *TINY_FLAGS, "--out", "p"],
            "plot-dataset": ["plot-dataset", "bad.npz", "--out", "x.png"],
            "refine": ["refine", "--rollouts", "bad.npz", "--workers", "1", "--out", "f.npz"]}[cmd]
    _unchanged(work, argv, made, 1, "bad.npz", field)


# ----------------------------------------------------------------------------- 7. leftovers
@pytest.mark.parametrize("extra,needle", [(["--only", "nope"], "nope"), (["--stack", "0"], "--stack")])
def test_a_refused_run_leaves_no_lock_file(made, work, extra, needle):
    """At 3cd1b8b `--only nope` and `--stack 0` left `runs/.small.lock` behind."""
    _unchanged(work, ["pipeline", "small", "--run", *extra], made, 1, needle)


def test_a_run_refused_inside_the_lock_removes_the_lock_it_made(made, work):
    """A runs folder that holds a run of other settings is refused under the lock: the lock file goes too."""
    spec = yaml.safe_load((work / "pipelines" / "small.yaml").read_text())
    (work / "runs" / "small" / "pendulum-sdp-n10-s0").mkdir(parents=True)
    (work / "runs" / "small" / "pendulum-sdp-n10-s0" / "loop_config.json").write_text(json.dumps({"task": "x"}))
    assert spec
    before = snapshot(work)
    r = runner.invoke(app, ["pipeline", "small", "--run", "--only", "pendulum-sdp-n10-s0"])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert snapshot(work) == before


# ----------------------------------------------------------------------------- 8. timing files
@pytest.mark.parametrize("artifact", ["data", "r", "pol"])
def test_a_timing_file_of_another_artifact_is_ignored(made, tmp_path, artifact):
    """`*.timing.json` are not DVC outputs: after `dvc checkout` restores another run's artifact, its timing
    file still describes the one made here. At 3cd1b8b it was read as the restored artifact's."""
    from sdp_cli.data.artifacts import IGNORED_TIMINGS, load_timing, timing_path

    src = made[artifact]
    dst = tmp_path / src.name
    (shutil.copytree if src.is_dir() else shutil.copy)(src, dst)
    shutil.copy(timing_path(src), timing_path(dst))
    IGNORED_TIMINGS.clear()
    assert load_timing(dst).get("created")                      # its own artifact: read
    target = dst / "checkpoint.pt" if dst.is_dir() else dst
    target.write_bytes(target.read_bytes() + b"\0")             # another artifact's bytes at the same path
    assert load_timing(dst) == {} and str(timing_path(dst)) in IGNORED_TIMINGS


@pytest.mark.parametrize("value", ["abc", "nan", "-1", "inf"])
def test_a_bad_solve_timeout_is_one_line_not_a_silent_default(value, monkeypatch):
    """SDP_SOLVE_TIMEOUT=abc used to fall back to the default without a word."""
    from typer.testing import CliRunner

    from sdp_cli.cli import app

    monkeypatch.setenv("SDP_SOLVE_TIMEOUT", value)
    r = CliRunner().invoke(app, ["tasks"])
    assert r.exit_code == 1 and "SDP_SOLVE_TIMEOUT must be a number of seconds" in r.output
    assert "Traceback" not in r.output
    monkeypatch.setenv("SDP_SOLVE_TIMEOUT", "0")
    assert CliRunner().invoke(app, ["tasks"]).exit_code == 0

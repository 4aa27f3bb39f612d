"""Same seed, same settings, same artifacts: every array equal, and the metadata equal except the
provenance (git revision, runtime); re-run at the same paths, the same bytes (what DVC hashes),
with the clock readings in the timing sidecars."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.policy.checkpoint import load_checkpoint
from synthetic_dataset import write_dataset

runner = CliRunner()
VOLATILE = {"provenance"}


def _same_artifact(a, b):
    (xa, ma), (xb, mb) = load_npz(a), load_npz(b)
    assert set(xa) == set(xb)
    for k in set(xa):
        np.testing.assert_array_equal(xa[k], xb[k], err_msg=k)
    def strip(m):   # (the two runs live in different folders: the policy path differs by design)
        m = {k: v for k, v in m.items() if k not in VOLATILE}
        m["config"] = {k: v for k, v in m["config"].items() if k != "policy"}
        return m

    assert strip(ma) == strip(mb)


def test_train_and_rollout_twice_give_the_same_artifacts(tmp_path):
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    runs = []
    for r in ("a", "b"):
        res = runner.invoke(app, ["train", "--data", str(data), "--method", "sdp", "--epochs", "3", "--horizon", "8",
                                  "--down-dims", "8,16", "--batch-size", "16", "--seed", "4", "--device", "cpu",
                                  "--out", str(tmp_path / r), "--no-progress"])
        assert res.exit_code == 0, res.output
        res = runner.invoke(app, ["rollout", "--policy", str(tmp_path / r), "--n", "3", "--seed", "2",
                                  "--t-a", "3", "--out", str(tmp_path / f"{r}.npz")])
        assert res.exit_code == 0, res.output
        runs.append(r)
    ca, cb = (load_checkpoint(tmp_path / r) for r in runs)
    for key in ("model", "ema_model"):
        for k in ca[key]:
            assert torch.equal(ca[key][k], cb[key][k]), k
    assert ca["provenance"]["torch_threads"] == 1 and ca["device"] == "cpu"
    _same_artifact(tmp_path / "a.npz", tmp_path / "b.npz")
    _, meta = load_npz(tmp_path / "a.npz")
    assert meta["device"] == "cpu" and meta["provenance"]["torch_threads"] == 1


def test_collect_twice_gives_the_same_dataset(tmp_path):
    for r in ("a", "b"):
        res = runner.invoke(app, ["collect", "--task", "pendulum", "--n-traj", "2", "--seed", "5", "--workers", "1",
                                  "--out", str(tmp_path / f"{r}.npz")])
        assert res.exit_code == 0, res.output
    xa, _ = load_npz(tmp_path / "a.npz")
    xb, _ = load_npz(tmp_path / "b.npz")
    for k in xa:
        np.testing.assert_array_equal(xa[k], xb[k], err_msg=k)


def _pipeline_commands(d) -> list[list[str]]:
    """collect -> train -> rollout -> refine -> evaluate into the folder ``d`` (a stage's commands)."""
    return [["collect", "--task", "pendulum", "--n-traj", "2", "--seed", "3", "--workers", "1",
             "--out", str(d / "data.npz")],
            ["train", "--data", str(d / "data.npz"), "--method", "sdp", "--epochs", "2", "--horizon", "8",
             "--down-dims", "8,16", "--batch-size", "16", "--seed", "1", "--device", "cpu", "--no-progress",
             "--out", str(d / "policy")],
            ["rollout", "--policy", str(d / "policy"), "--n", "2", "--seed", "0", "--t-a", "4",
             "--out", str(d / "rollout.npz")],
            ["refine", "--rollouts", str(d / "rollout.npz"), "--workers", "1", "--out", str(d / "refined.npz")],
            ["evaluate", "--rollouts", str(d / "rollout.npz"), "--refined", str(d / "refined.npz"),
             "--out", str(d / "eval.csv"), "--metrics", str(d / "metrics.json")]]


PIPELINE_OUTS = ["data.npz", "policy/checkpoint.pt", "policy/metrics.csv", "rollout.npz", "refined.npz", "eval.csv",
                 "metrics.json"]


def _run_all(cmds):
    for c in cmds:
        r = runner.invoke(app, c)
        assert r.exit_code == 0, (c[0], r.output)


def test_rerun_at_the_same_paths_writes_the_same_bytes(tmp_path):
    """What a forced `dvc repro` does: delete the outputs, run the same commands again. Every output
    (dataset, checkpoint, metrics.csv, rollouts, refined, eval.csv, metrics JSON) has the same SHA-256;
    only the timing sidecars (not DVC outputs) differ."""
    import shutil

    from sdp_cli.data.artifacts import file_sha256, load_timing

    d = tmp_path / "run"
    hashes = []
    for _ in range(2):
        shutil.rmtree(d, ignore_errors=True)
        _run_all(_pipeline_commands(d))
        hashes.append({o: file_sha256(d / o) for o in PIPELINE_OUTS})
    assert hashes[0] == hashes[1]
    assert load_timing(d / "data.npz")["wall_time"] > 0 and load_timing(d / "policy")["wall_time"] > 0
    assert load_timing(d / "rollout.npz")["rollout_time"] > 0
    assert len(load_timing(d / "refined.npz")["inst_pol_time"]) == 2
    from sdp_cli.algorithm.evaluate import read_evaluation

    row = read_evaluation(d / "eval.csv").iloc[0]
    assert row.rollout_time > 0 and row.to_alone_solve_time_mean > 0
    assert "rollout_time" not in open(d / "eval.csv").readline()


def test_the_same_commands_in_another_clone_write_the_same_bytes(tmp_path, monkeypatch):
    """`dvc repro` in a second clone: the same relative commands run from another root folder give
    outputs with the same SHA-256 (artifacts record paths relative to themselves, never absolute
    ones), and the recorded paths still lead to the files they name."""
    from sdp_cli.data.artifacts import file_sha256
    from sdp_cli.algorithm.evaluate import read_manifest
    from sdp_cli.policy.api import load_policy

    hashes = []
    for clone in ("clone_a", "elsewhere/clone_b"):
        root = tmp_path / clone
        root.mkdir(parents=True)
        monkeypatch.chdir(root)
        _run_all(_pipeline_commands(Path("runs")))
        hashes.append({o: file_sha256(root / "runs" / o) for o in PIPELINE_OUTS})
    assert hashes[0] == hashes[1]
    monkeypatch.chdir(tmp_path)   # resolved from any working folder
    b = tmp_path / "elsewhere/clone_b/runs"
    assert Path(load_policy(b / "policy").dataset_info["path"]) == (b / "data.npz").resolve()
    entry = read_manifest(b / "eval.manifest.json")["entries"][0]
    assert Path(entry["data"]) == (b / "data.npz").resolve() and Path(entry["policy"]) == (b / "policy").resolve()

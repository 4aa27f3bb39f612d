"""Same seed, same settings, same artifacts: every array equal, and the metadata equal except the
creation time, the provenance (git revision, runtime) and timing fields."""

from __future__ import annotations

import numpy as np
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.policy.checkpoint import load_checkpoint
from synthetic_dataset import one_torch_thread, write_dataset  # noqa: F401 (autouse fixture)

runner = CliRunner()
VOLATILE = {"created", "provenance"}
TIMING_ARRAYS = {"rollout_time"}


def _same_artifact(a, b):
    (xa, ma), (xb, mb) = load_npz(a), load_npz(b)
    assert set(xa) == set(xb)
    for k in set(xa) - TIMING_ARRAYS:
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
    xa.pop("solve_time")
    xb, _ = load_npz(tmp_path / "b.npz")
    for k in xa:
        np.testing.assert_array_equal(xa[k], xb[k], err_msg=k)

"""Slow smoke test: collect -> train -> rollout -> refine -> evaluate -> report for the UR5 and the
quadrotor, tiny budgets.

Marked slow (deselected by default; `python -m pytest -m slow`): the first solve of each task
compiles its casadi problem (minutes for the UR5 on 2 cores, then cached in $SDP_CACHE_DIR).
State-controlled policies go through inverse dynamics (RNEA / thrust allocation) in the rollout.
"""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz

runner = CliRunner()


@pytest.mark.slow
@pytest.mark.parametrize("task", ["ur5-fixed", "quadrotor-1"])
@pytest.mark.parametrize("method", ["sdp", "pddp_s"])
def test_collect_train_rollout_refine(tmp_path, task, method):
    data, pol, ro, rf = (tmp_path / n for n in ("d.npz", "policy", "eval/rollout.npz", "eval/refined.npz"))
    ro.parent.mkdir()
    steps = [
        ["collect", "--task", task, "--n-traj", "2", "--seed", "0", "--out", str(data), "--workers", "1"],
        ["train", "--data", str(data), "--method", method, "--epochs", "2", "--horizon", "32",
         "--batch-size", "16", "--device", "cpu", "--no-progress", "--out", str(pol)]
        + (["--sobolev-alpha", "0.001"] if task.startswith("quadrotor") else []),
        ["rollout", "--policy", str(pol), "--task", task, "--n", "2", "--t-a", "16", "--out", str(ro)],
        ["refine", "--rollouts", str(ro), "--out", str(rf), "--workers", "1"],
        ["evaluate", "--rollouts", str(ro), "--refined", str(rf), "--out", str(tmp_path / "eval" / "eval.csv")],
        ["report", "--runs", str(tmp_path / "eval"), "--out", str(tmp_path / "results" / "smoke")],
    ]
    for args in steps:
        r = runner.invoke(app, args)
        assert r.exit_code == 0, (args[0], r.output)
    rollouts, _ = load_npz(ro, kind="rollout")
    assert rollouts["X"].shape[0] == 2 and np.all(np.isfinite(rollouts["max_violation"]) | rollouts["diverged"])
    refined, meta = load_npz(rf, kind="dataset")
    assert meta["task"] == task and len(refined["inst_winner"]) == 2
    assert refined["K"].shape[2:] == (refined["U"].shape[2], refined["A"].shape[2])
    # the report draws Fig. 3/4-style trajectories (top view, with the columns for the quadrotor)
    res = tmp_path / "results" / "smoke"
    for name in (f"traj_{task}.png", f"table2c_{task}.md", f"fig2b_{task}.png", "README.md"):
        assert (res / name).is_file(), name

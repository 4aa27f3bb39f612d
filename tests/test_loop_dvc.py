"""One Algorithm 1: `dvc repro` of an experiment and `sdp loop` with the same settings write the same
artifacts (the DVC stage runs the experiment's runs through sdp_cli.experiments.runner, i.e. sdp_cli.algorithm.loop.run_loop)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz

ROOT = Path(__file__).resolve().parents[1]
TINY = """description: a tiny loop, to compare dvc repro with sdp loop
groups:
  - {task: pendulum, methods: [dp], seeds: [1], n_traj: [2], n_algo: 2, epochs: 2, horizon: 8, t_a: 4,
     n_test: 2, train: {batch_size: 8}}
"""
LOOP = ["--task", "pendulum", "--method", "dp", "--seed", "1", "--n-traj", "2", "--n-algo", "2", "--epochs", "2",
        "--horizon", "8", "--t-a", "4", "--n-test", "2", "--batch-size", "8", "--workers", "1", "--device", "cpu"]


def test_dvc_repro_and_sdp_loop_write_the_same_artifacts(tmp_path):
    if shutil.which("dvc", path=str(Path(sys.executable).parent)) is None:
        pytest.fail("dvc is not installed in this environment (pip install -e '.[test]')")
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    work = tmp_path / "repo"
    for f in files:
        if not f.startswith(("runs/", "results/")) and f != "dvc.lock" and (ROOT / f).is_file():
            (work / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, work / f)
    (work / "pipelines" / "tiny.yaml").write_text(TINY)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "SDP_WORKERS": "1"}
    subprocess.run(["git", "init", "-q"], cwd=work, check=True)
    for cmd in (["sdp", "pipeline", "tiny"], ["dvc", "repro", "group"]):
        r = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    r = CliRunner().invoke(app, ["loop", *LOOP, "--out", str(tmp_path / "loop"), "--no-progress"])
    assert r.exit_code == 0, r.output
    dvc_run, loop_run = work / "runs" / "tiny" / "pendulum-dp-n2-s1", tmp_path / "loop"
    for k in (0, 1):
        a, _ = load_npz(dvc_run / f"it{k}" / "data.npz")
        b, _ = load_npz(loop_run / f"it{k}" / "data.npz")
        np.testing.assert_array_equal(a["X"], b["X"])
        np.testing.assert_array_equal(a["K"], b["K"])
        ca = torch.load(dvc_run / f"it{k}" / "policy" / "checkpoint.pt", weights_only=True)
        cb = torch.load(loop_run / f"it{k}" / "policy" / "checkpoint.pt", weights_only=True)
        for key in ca["ema_model"]:
            assert torch.equal(ca["ema_model"][key], cb["ema_model"][key]), (k, key)
        a, _ = load_npz(dvc_run / f"it{k}" / "eval" / "rollout_ta4.npz")
        b, _ = load_npz(loop_run / f"it{k}" / "eval" / "rollout_ta4.npz")
        np.testing.assert_array_equal(a["X"], b["X"])
    cols = ["iteration", "policy_cost_mean", "refined_cost_mean", "to_alone_cost_mean", "success_rate"]
    pd.testing.assert_frame_equal(pd.read_csv(dvc_run / "summary.csv")[cols], pd.read_csv(loop_run / "summary.csv")[cols])

"""`sdp pipeline NAME --run` (sdp_cli.experiments.runner): the runs of an experiment in parallel, resumable, with the
same results as one after another; a killed worker's run is redone."""

from __future__ import annotations

import functools

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.errors import SdpError
from sdp_cli.experiments.pipeline import loop_configs
from sdp_cli.experiments.runner import run_group

TINY = """
description: two runs of a tiny loop
groups:
  - task: pendulum
    methods: [dp]
    seeds: [0, 1]
    n_traj: [2]
    epochs: 2
    save_at: [1]
    horizon: 8
    t_a: 4
    n_test: 2
    train: {batch_size: 8}
"""
RUNS = ["pendulum-dp-n2-s0", "pendulum-dp-n2-s1"]
VALUES = ["iteration", "epochs", "t_a", "policy_cost_mean", "success_rate", "refined_cost_mean",
          "to_alone_cost_mean", "refined_iterations_mean"]


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    r = tmp_path_factory.mktemp("exp")
    (r / "pipelines").mkdir()
    (r / "pipelines" / "tiny.yaml").write_text(TINY)
    return r


@pytest.fixture(scope="module")
def sequential(root):
    """The reference: the runs one after another in this process."""
    out = root / "seq"
    df = run_group("tiny", out, executor="local", workers=1, device="cpu", root=root, log=lambda s: None, stack=1)
    return out, df


def _table(df):
    return df.sort_values(["run", "epochs"])[["run", *VALUES]].reset_index(drop=True)


def _same_runs(a, b):
    for run in RUNS:
        ca = torch.load(a / run / "it0" / "policy" / "checkpoint.pt", weights_only=True)
        cb = torch.load(b / run / "it0" / "policy" / "checkpoint.pt", weights_only=True)
        for k in ca["ema_model"]:
            assert torch.equal(ca["ema_model"][k], cb["ema_model"][k]), (run, k)
        for name in ("rollout_ta4.npz", "rollout_e1-ta4.npz"):
            xa, _ = load_npz(a / run / "it0" / "eval" / name)
            xb, _ = load_npz(b / run / "it0" / "eval" / name)
            np.testing.assert_array_equal(xa["X"], xb["X"], err_msg=f"{run}/{name}")


def test_runs_of_an_experiment_are_loop_configs(root):
    from sdp_cli.experiments.experiment import load_experiment

    spec = load_experiment("tiny", root)
    cfgs = loop_configs("tiny", spec)
    assert list(cfgs) == RUNS
    assert cfgs[RUNS[1]].seed == 1 and cfgs[RUNS[1]].collect_seed(0) == 1000 and cfgs[RUNS[0]].save_at == [1]
    assert len(loop_configs("tiny", spec)) == 2


def test_sequential_runs_evaluate_both_budgets(sequential):
    out, df = sequential
    assert sorted(df.run.unique()) == RUNS
    assert sorted(df.epochs.unique()) == [1, 2]      # save_at 1 and the final epoch 2, from one training
    assert (out / RUNS[0] / "it0" / "policy" / "epoch_1.pt").is_file()
    summary = pd.read_csv(out / RUNS[0] / "summary.csv")
    assert len(summary) == 2 and np.isfinite(summary.policy_cost_mean).all()


def test_parallel_runs_equal_sequential(root, sequential):
    out = root / "par"
    df = run_group("tiny", out, executor="local", workers=2, device="cpu", root=root, log=lambda s: None, stack=1)
    pd.testing.assert_frame_equal(_table(df), _table(sequential[1]))
    _same_runs(out, sequential[0])


def test_killed_worker_run_is_redone_and_equals_sequential(root, sequential, tmp_path):
    from executor_jobs import die_once_after_training

    out = root / "killed"
    job = functools.partial(die_once_after_training, str(tmp_path / "killed-once"))
    df = run_group("tiny", out, executor="local", workers=2, device="cpu", root=root, log=lambda s: None, job=job,
                   stack=1)
    assert (tmp_path / "killed-once").exists()       # a worker did die
    pd.testing.assert_frame_equal(_table(df), _table(sequential[1]))
    _same_runs(out, sequential[0])


def test_resume_redoes_nothing_and_only_selects_runs(root, sequential):
    out, _ = sequential
    files = [p for p in out.rglob("*") if p.is_file() and p.suffix in (".npz", ".pt")]
    before = {p: p.stat().st_mtime_ns for p in files}
    df = run_group("tiny", out, executor="local", workers=1, device="cpu", root=root, only=[RUNS[1]],
                   log=lambda s: None)
    assert set(df.run) == {RUNS[1]}
    assert {p: p.stat().st_mtime_ns for p in files} == before
    with pytest.raises(SdpError, match="has no run"):
        run_group("tiny", out, workers=1, root=root, only=["nope"], log=lambda s: None)


def test_cli_run_errors_are_one_line(root, monkeypatch):
    monkeypatch.chdir(root)
    runner = CliRunner()
    r = runner.invoke(app, ["pipeline", "tiny", "--run", "--executor", "mpi"])
    assert r.exit_code == 1 and "unknown executor 'mpi'" in r.output
    monkeypatch.setenv("SDP_WORKERS", "two")
    r = runner.invoke(app, ["pipeline", "tiny", "--run"])
    assert r.exit_code == 1 and "SDP_WORKERS must be an integer" in r.output
    r = runner.invoke(app, ["pipeline", "tiny", "--run", "--estimate"])
    assert r.exit_code == 1 and "exclude each other" in r.output


def test_dvc_mode_never_deletes_and_restarts_only_another_results_version(root, sequential, tmp_path):
    """What the DVC stage runs (--restart-changed): another code revision alone resumes the run (a comment
    edit must not restart it); another results version, or none recorded (older runs), moves the run to
    superseded/<experiment>/ with its files intact and starts it over. No run is ever deleted."""
    import json
    import shutil

    from sdp_cli import RESULTS_VERSION
    from sdp_cli.experiments.runner import superseded_dir

    out = tmp_path / "runs" / "tiny"
    shutil.copytree(sequential[0] / RUNS[0], out / RUNS[0])
    cfg = out / RUNS[0] / "loop_config.json"
    assert json.loads(cfg.read_text())["results_version"] == RESULTS_VERSION
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "code_rev": "0" * 40}))
    ck = out / RUNS[0] / "it0" / "policy" / "checkpoint.pt"
    before = ck.stat().st_mtime_ns
    for restart in (False, True):                                  # other code: resumed, nothing redone
        run_group("tiny", out, workers=1, device="cpu", root=root, only=[RUNS[0]], restart_changed=restart,
                  log=lambda s: None)
        assert ck.stat().st_mtime_ns == before
    old = {k: v for k, v in json.loads(cfg.read_text()).items() if k != "results_version"}   # a version-1 run
    cfg.write_text(json.dumps(old))
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.algorithm.loop import check_resume
    from sdp_cli.experiments.pipeline import loop_configs

    with pytest.raises(SdpError, match="results_version=1"):
        check_resume(loop_configs("tiny", load_experiment("tiny", root))[RUNS[0]], out / RUNS[0], same_results=True)
    files = sorted(p.relative_to(out / RUNS[0]) for p in (out / RUNS[0]).rglob("*"))
    logs = []
    df = run_group("tiny", out, workers=1, device="cpu", root=root, only=[RUNS[0]], restart_changed=True,
                   log=logs.append)
    moved = list(superseded_dir(out).iterdir())
    assert len(moved) == 1 and moved[0].name.startswith(RUNS[0] + "-")
    assert sorted(p.relative_to(moved[0]) for p in moved[0].rglob("*")) == files      # kept, every file
    assert superseded_dir(out) == tmp_path / "runs" / "superseded" / "tiny"             # outside the DVC output
    assert any("results_version" in s and str(moved[0]) in s for s in logs)
    assert ck.stat().st_mtime_ns != before
    pd.testing.assert_frame_equal(_table(df), _table(sequential[1][sequential[1].run == RUNS[0]]))


def test_status_reports_each_run_from_its_folder(root, sequential, tmp_path, monkeypatch):
    """`sdp pipeline NAME --status`: done runs, a run interrupted after its first evaluation, one not
    started, and a folder of other settings, read from the folders only."""
    import json
    import shutil

    from sdp_cli.experiments.runner import run_status

    out = tmp_path / "runs"
    shutil.copytree(sequential[0] / RUNS[0], out / RUNS[0])
    st = run_status("tiny", out, root=root).set_index("run")
    assert st.loc[RUNS[0]].tolist() == ["1/1", "done"] and st.loc[RUNS[1]].tolist() == ["0/1", "not started"]
    (out / RUNS[0] / "summary.csv").unlink()                        # interrupted before the summary
    assert run_status("tiny", out, root=root).set_index("run").loc[RUNS[0], "state"] == "in progress"
    cfg = json.loads((out / RUNS[0] / "loop_config.json").read_text())
    cfg["train"]["data"]["epochs"] = 99
    (out / RUNS[0] / "loop_config.json").write_text(json.dumps(cfg))
    assert run_status("tiny", out, root=root).set_index("run").loc[RUNS[0], "state"] == "other settings"
    monkeypatch.chdir(root)
    r = CliRunner().invoke(app, ["pipeline", "tiny", "--status", "--out", str(out)])
    assert r.exit_code == 0 and "1 not started, 1 other settings" in r.output
    assert sorted(p.name for p in out.iterdir()) == [RUNS[0]]          # reads only


SIX = TINY.replace("seeds: [0, 1]", "seeds: [0, 1, 2]").replace("n_traj: [2]", "n_traj: [2, 3]")


def test_compatible_runs_train_as_one_stack_and_equal_their_solo_runs(root):
    """`sdp pipeline --run` packs compatible one-iteration runs (3 seeds x 2 dataset sizes) into one stack: the
    same evaluations as the runs trained one by one, to float32 rounding."""
    from sdp_cli.experiments.runner import pack, split_even

    (root / "pipelines" / "six.yaml").write_text(SIX)
    runs = loop_configs("six", __import__("sdp_cli.experiments.experiment", fromlist=["x"]).load_experiment("six", root))
    size = {n: [r for r in runs if runs[r].n_traj_at(0) == n] for n in (2, 3)}
    assert [len(size[2]), len(size[3])] == [3, 3]
    # one dataset size per stack (a stack pads every batch to its largest), the larger first; split evenly
    assert pack(runs, 8) == [size[3], size[2]] and pack(runs, 3) == [size[3], size[2]]
    assert pack(runs, 2) == [size[3][:2], size[3][2:], size[2][:2], size[2][2:]]
    assert pack(runs, 1) == [[r] for r in runs]
    assert split_even(list("abcdefghij"), 8) == [list("abcde"), list("fghij")]
    assert split_even(list("abcdefg"), 3) == [list("abc"), list("de"), list("fg")] and split_even(["a"], 8) == [["a"]]
    solo = run_group("six", root / "six-solo", executor="local", workers=2, device="cpu", root=root,
                     log=lambda s: None, stack=1)
    stacked = run_group("six", root / "six-stack", executor="local", workers=2, device="cpu", root=root,
                        log=lambda s: None)
    a = solo.sort_values(["run", "epochs"]).reset_index(drop=True)
    b = stacked.sort_values(["run", "epochs"]).reset_index(drop=True)
    assert list(a.run) == list(b.run) and len(set(a.run)) == 6
    for col in ("policy_cost_mean", "success_rate", "to_alone_cost_mean"):
        np.testing.assert_allclose(b[col], a[col], rtol=1e-3, err_msg=col)
    ck = torch.load(root / "six-stack" / "pendulum-dp-n3-s2" / "it0" / "policy" / "checkpoint.pt", weights_only=True)
    assert ck["finished"] and ck["dataset"]["n_traj"] == 3     # each member's checkpoint: a solo one


LOOPS = """
description: two-iteration loops of one network shape, two methods, two seeds, two T_a
groups:
  - task: pendulum
    methods: [sdp, dp]
    seeds: [0, 1]
    n_traj_schedule: [2, 3]
    n_algo: 2
    epochs: 2
    horizon: 8
    t_a: 4
    n_test: 2
    train: {batch_size: 8, down_dims: [8, 16], n_groups: 4, step_embed_dim: 8}
  - task: pendulum
    methods: [dp]
    seeds: [2]
    n_traj_schedule: [2, 3]
    n_algo: 2
    epochs: 2
    horizon: 8
    t_a: 3
    n_test: 2
    train: {batch_size: 8, down_dims: [8, 16], n_groups: 4, step_embed_dim: 8}
"""


def test_loops_of_several_iterations_train_as_one_stack_in_lockstep(root):
    """Loops of as many iterations, buffer rule and dataset sizes stack too (issue "Training 2-3x faster"), keyed
    by network shape and tangent pass (other seeds and T_a in one stack): at each iteration every member collects (warm-started by its own previous policy) and merges its own buffer, then
    the members train as one stack, each warm-started from its own previous policy. The evaluations equal the
    loops run alone, to float32 rounding (the stack's grouped kernels sum in another order)."""
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.policy.checkpoint import load_checkpoint
    from sdp_cli.experiments.runner import pack

    (root / "pipelines" / "loops.yaml").write_text(LOOPS)
    runs = loop_configs("loops", load_experiment("loops", root))
    assert len(runs) == 5 and {c.method for c in runs.values()} == {"sdp", "dp"}
    # one stack per tangent pass (SDP's, DP's none): seeds and T_a mixed within each
    sdp, dp = ([r for r in runs if runs[r].method == m] for m in ("sdp", "dp"))
    assert pack(runs, 8) == [sdp, dp] and pack(runs, 1) == [[r] for r in runs]
    lines = []
    solo = run_group("loops", root / "loops-solo", executor="local", workers=1, device="cpu", root=root,
                     log=lambda s: None, stack=1)
    stacked = run_group("loops", root / "loops-stack", executor="local", workers=1, device="cpu", root=root,
                        log=lines.append)
    a = solo.sort_values(["run", "iteration", "epochs"]).reset_index(drop=True)
    b = stacked.sort_values(["run", "iteration", "epochs"]).reset_index(drop=True)
    assert list(a.run) == list(b.run) and list(b.iteration.unique()) == [0, 1]
    for col in ("policy_cost_mean", "success_rate", "to_alone_cost_mean"):
        np.testing.assert_allclose(b[col], a[col], rtol=1e-3, err_msg=col)
    for run in runs:
        ck = load_checkpoint(root / "loops-stack" / run / "it1" / "policy" / "checkpoint.pt")
        assert ck["finished"] and ck["init"] and ck["dataset"]["n_traj"] == 3    # warm start, its own it1 data
        ref = load_checkpoint(root / "loops-solo" / run / "it1" / "policy" / "checkpoint.pt")
        for k, v in ref["ema_model"].items():
            torch.testing.assert_close(ck["ema_model"][k], v, rtol=1e-3, atol=1e-3)

"""`sdp loop` (Algorithm 1 end to end): artifacts per iteration, resume, settings guard."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz, resolve_recorded
from sdp_cli.algorithm.evaluate import is_timing_column

runner = CliRunner()


def _loop(out, *extra):
    return runner.invoke(app, ["loop", "--task", "pendulum", "--method", "sdp", "--n-algo", "2", "--n-traj", "3",
                               "--epochs", "2", "--horizon", "8", "--t-a", "4", "--n-test", "3", "--workers", "1",
                               "--batch-size", "16", "--out", str(out), *extra])


@pytest.fixture(scope="module")
def loop_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("loop") / "run"
    r = _loop(out)
    assert r.exit_code == 0, r.output
    return out


def test_loop_writes_every_iteration(loop_dir):
    for k in (0, 1):
        for name in ("data.npz", "policy/checkpoint.pt", "eval/rollout_ta4.npz", "eval/refined_ta4.npz",
                     "eval/eval.csv"):
            assert (loop_dir / f"it{k}" / name).is_file(), f"it{k}/{name}"
    summary = pd.read_csv(loop_dir / "summary.csv")
    assert list(summary.iteration) == [0, 1] and (summary.n == 3).all() and (summary.t_a == 4).all()
    assert (summary.n_algo == 2).all()          # what "finished" means for the report and the ledger
    assert not [c for c in summary if is_timing_column(c)]   # hashed by DVC: no clock readings
    # iteration 0 collects from the naive guess, iteration 1 warm-starts TO with iteration 0's policy
    _, m0 = load_npz(loop_dir / "it0" / "data.npz", kind="dataset")
    _, m1 = load_npz(loop_dir / "it1" / "data.npz", kind="dataset")
    assert m0["config"]["policy"] is None
    # recorded relative to the dataset's folder, and resolving there
    assert m1["config"]["policy"] == "../it0/policy" and m1["config"]["t_a"] == 4
    assert resolve_recorded(m1["config"]["policy"], loop_dir / "it1") == (loop_dir / "it0" / "policy").resolve()
    assert m0["config"]["seed"] != m1["config"]["seed"]
    # the warm-started collection and the evaluation's refinement share one schema of per-instance records
    d1, _ = load_npz(loop_dir / "it1" / "data.npz", kind="dataset")
    f1, _ = load_npz(loop_dir / "it1" / "eval" / "refined_ta4.npz", kind="dataset")
    inst = sorted(k for k in f1 if k.startswith("inst_"))
    assert inst == sorted(k for k in d1 if k.startswith("inst_") and k != "inst_index")
    assert set(d1["index"]) <= set(d1["inst_index"]) and len(d1["inst_winner"]) == len(d1["inst_index"])
    for i, idx in enumerate(d1["index"]):      # each kept trajectory is its instance's ArgminCost
        j = list(d1["inst_index"]).index(idx)
        cands = [c for c, ok in ((d1["inst_pol_cost"][j], d1["inst_pol_converged"][j]),
                                 (d1["inst_base_cost"][j], d1["inst_base_converged"][j])) if ok]
        assert d1["cost"][i] == pytest.approx(min(cands))


def test_loop_resume_recomputes_nothing_and_refuses_other_settings(loop_dir):
    files = [p for p in loop_dir.rglob("*") if p.is_file() and p.suffix in (".npz", ".pt")]
    before = {p: p.stat().st_mtime_ns for p in files}
    r = _loop(loop_dir)
    assert r.exit_code == 0, r.output
    assert {p: p.stat().st_mtime_ns for p in files} == before
    r = _loop(loop_dir, "--seed", "3")
    assert r.exit_code == 1 and "other settings" in r.output and "seed=0" in r.output
    foreign = loop_dir.parent / "foreign"
    (foreign / "it0").mkdir(parents=True)      # e.g. an old layout's folder: never resumed as if it were a loop
    r = _loop(foreign)
    assert r.exit_code == 1 and "no loop_config.json" in r.output


def test_loop_without_eval_refine_reports_policy_metrics_only(tmp_path):
    out = tmp_path / "run"
    r = runner.invoke(app, ["loop", "--task", "pendulum", "--method", "dp", "--n-traj", "2", "--epochs", "1",
                            "--horizon", "8", "--t-a", "4", "--n-test", "2", "--workers", "1", "--batch-size", "8",
                            "--no-eval-refine", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert (out / "it0" / "eval" / "rollout_ta4.npz").is_file()
    assert not (out / "it0" / "eval" / "refined_ta4.npz").exists()
    summary = pd.read_csv(out / "summary.csv")
    assert summary.n.tolist() == [2] and "policy_cost_mean" in summary and "refined_cost_mean" not in summary
    # turning refine on is a resumable change: the same folder gains the refined evaluation
    r = runner.invoke(app, ["loop", "--task", "pendulum", "--method", "dp", "--n-traj", "2", "--epochs", "1",
                            "--horizon", "8", "--t-a", "4", "--n-test", "2", "--workers", "1", "--batch-size", "8",
                            "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert (out / "it0" / "eval" / "refined_ta4.npz").is_file()
    assert "refined_cost_mean" in pd.read_csv(out / "summary.csv")


def test_loop_executor_options_are_validated(tmp_path):
    r = _loop(tmp_path / "x", "--executor", "mpi")
    assert r.exit_code == 1 and "unknown executor 'mpi'" in r.output
    assert not (tmp_path / "x").exists()


def test_report_of_a_loop_run(loop_dir, tmp_path):
    res = tmp_path / "results" / "tiny"
    r = runner.invoke(app, ["report", "--runs", str(loop_dir.parent), "--out", str(res), "--experiment", "tiny",
                            "--metrics", str(tmp_path / "metrics" / "tiny.json")])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "metrics" / "tiny.json").read_text())   # DVC metrics: the last iteration
    last_row = pd.read_csv(loop_dir / "summary.csv").query("iteration == 1").iloc[0]
    assert m["pendulum"]["sdp"]["iteration"] == 1 and m["pendulum"]["sdp"]["seeds"] == 1
    assert m["pendulum"]["sdp"]["policy_cost_mean"] == pytest.approx(last_row.policy_cost_mean)
    assert m["pendulum"]["sdp"]["to_alone_cost_mean"] == pytest.approx(last_row.to_alone_cost_mean)
    for name in ("all_runs.csv", "fig1_pendulum.png", "fig2a_pendulum.csv", "fig2b_pendulum.png",
                 "table2c_pendulum.md", "traj_pendulum.png", "README.md"):
        assert (res / name).is_file(), name
    fig2a = pd.read_csv(res / "fig2a_pendulum.csv")
    assert sorted(fig2a.iteration.unique()) == [0, 1]
    assert "[tiny](tiny/README.md)" in (tmp_path / "results" / "README.md").read_text()
    timing = pd.read_csv(res / "timing_pendulum.csv")
    assert list(timing.iteration) == [0, 1]
    for k, row in timing.iterrows():
        metrics = pd.read_csv(loop_dir / f"it{k}" / "policy" / "metrics.csv")
        sidecar = json.loads((loop_dir / f"it{k}" / "policy.timing.json").read_text())
        assert row.train_steps == metrics.step.iloc[-1] and row.train_s == pytest.approx(sidecar["wall_time"])
        assert row.train_s > 0 and "wall_time" not in metrics
        assert row.collect_solve_s > 0 and row.eval_rollout_s > 0
        assert row.collect_wall_s >= row.collect_solve_s     # the stage's wall time, not only the solver's
        assert str(row.eval_t_a_values) == "4"                # the T_a values, not their count
        # total: the stages' measured wall times; the evaluation's includes its rollouts and solves
        assert row.total_measured and row.eval_wall_s >= row.eval_rollout_s + row.eval_solve_s
        assert row.total_s == pytest.approx(row.collect_wall_s + row.train_s + row.eval_wall_s)
    # one seed: no confidence interval ("n/a", with the seed count), never a 0.0 that reads as certainty
    raw = pd.read_csv(res / "fig2a_pendulum.csv", keep_default_na=False)
    assert set(raw.ci95.astype(str)) == {"n/a"} and set(fig2a.n_seeds) == {1}
    t2c = pd.read_csv(res / "table2c_pendulum.csv")
    assert {"policy cost (median)", "policy success rate", "TO iterations warm-started by the policy"} <= set(t2c)
    last = pd.read_csv(loop_dir / "summary.csv").query("iteration == 1").iloc[0]
    assert t2c["policy success rate"].iloc[0] == pytest.approx(last.success_rate)
    assert t2c["policy cost (median)"].iloc[0] == pytest.approx(last.policy_cost_median)
    assert "no `pipelines/tiny.yaml`" in (res / "README.md").read_text()
    # data series for `dvc plots`: one training curve per iteration (the metrics, thinned), loop costs per method
    curves = sorted((res / "curves").glob("*.csv"))
    assert [p.name[-8:] for p in curves] == ["-it0.csv", "-it1.csv"]
    c = pd.read_csv(curves[0])
    metrics = pd.read_csv(loop_dir / "it0" / "policy" / "metrics.csv")
    assert list(c.columns) == ["step", "epoch", "loss", "dp", "sobolev", "lr"] and len(c) <= 500
    assert c.step.iloc[-1] == metrics.step.iloc[-1] and c.loss.iloc[0] == pytest.approx(metrics.loss.iloc[0])
    loop = pd.read_csv(res / "loop" / "pendulum-sdp.csv")
    assert list(loop.iteration) == [0, 1] and loop.policy.tolist() == pytest.approx(
        pd.read_csv(loop_dir / "summary.csv").policy_cost_mean.tolist())
    # a second report over fewer runs removes what the first wrote and this one does not; NOTES.md stays
    (res / "curves" / "old-run-it0.csv").write_text("step,loss\n")
    (res / "fig1_acrobot.png").write_bytes(b"old")
    (res / "NOTES.md").write_text("hand-written")
    r = runner.invoke(app, ["report", "--runs", str(loop_dir.parent), "--out", str(res), "--experiment", "tiny"])
    assert r.exit_code == 0, r.output
    assert not (res / "fig1_acrobot.png").exists() and (res / "NOTES.md").read_text() == "hand-written"
    assert not (res / "curves" / "old-run-it0.csv").exists()
    assert (res / "fig2a_pendulum.csv").is_file()
    # the refine artifacts carry TO alone and refined solutions for the trajectory plot
    f, _ = load_npz(loop_dir / "it1" / "eval" / "refined_ta4.npz", kind="dataset")
    assert f["inst_base_X"].shape == (3, 101, 2) and bool(f["inst_base_converged"].all())
    assert not pd.isna(f["inst_base_X"]).any()


def test_trajectory_figure_draws_later_methods_thinner_so_coinciding_paths_all_show(loop_dir, monkeypatch):
    """Two methods whose rollouts coincide (here the same files under two names): the one drawn first is wider,
    so it shows on both sides of the one drawn over it (SDP's line hid PDDP+S's on quadrotor-0, both 1.4 wide)."""
    import importlib

    from sdp_cli.report.runs import load_runs

    traj = importlib.import_module("sdp_cli.report.figures.traj")     # the module (the package exports a function)
    drawn = []
    monkeypatch.setattr(traj, "save_fig", lambda fig, path: drawn.append(fig) or path)
    d = load_runs(loop_dir.parent)
    both = pd.concat([d, d.assign(method="dp", run="dp-copy")], ignore_index=True)
    traj.trajectories(both, "pendulum", loop_dir.parent, n_show=2)
    fig = drawn.pop()
    for ax in fig.axes:
        width = {ln.get_label(): ln.get_linewidth() for ln in ax.get_lines()}
        # SDP sorts after DP, so it is drawn over DP's line: DP's is the wider, each refined line too
        assert width["TO alone (naive guess)"] > width["DP policy"] > width["SDP policy"] >= 1.4, width
        assert width["refined from DP"] > width["refined from SDP"] >= 1.0, width
    traj.pyplot().close(fig)

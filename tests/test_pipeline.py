"""Experiment files (pipelines/*.yaml): every run is a valid `sdp loop` (one Algorithm 1 for sdp loop,
`sdp pipeline --run` and DVC), selected into params.yaml for the DVC stage `group`."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sdp_cli.errors import SdpError
from sdp_cli.experiments.experiment import run_names
from sdp_cli.experiments.experiment import load_experiment
from sdp_cli.experiments.pipeline import loop_configs, select_experiment
from sdp_cli.tasks import task_names

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "pipelines").glob("*.yaml"))


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_is_a_set_of_valid_loops(name):
    spec = load_experiment(name, root=ROOT)
    runs = loop_configs(name, spec)             # every run validated as an `sdp loop` (task, method, T_a, options)
    assert runs and list(runs) == run_names(name, spec)
    assert {c.task for c in runs.values()} <= set(task_names())
    for c in runs.values():                     # the collection seeds of run s never meet another run's
        assert [c.collect_seed(k) for k in range(c.n_algo)] == [1000 * c.seed + k for k in range(c.n_algo)]
    assert isinstance(spec["groups"], dict)     # keyed by name: DVC's -S can address a group's setting


def test_fig2_runs_and_selection(tmp_path):
    runs = loop_configs("fig2", load_experiment("fig2", root=ROOT))
    # 4 methods x 5 seeds, twice: the loop's TO by box-FDDP (the paper's family, runs tagged -ddp) and by fatrop
    assert len(runs) == 2 * 4 * 5 and {c.seed for c in runs.values()} == {0, 1, 2, 3, 4}
    assert {n for n, c in runs.items() if c.to == "ddp"} == {n for n in runs if n.endswith("-ddp")}
    assert sum(c.to == "ddp" for c in runs.values()) == 20
    for name in ("double_pendulum-sdp-n30-s0", "double_pendulum-sdp-n30-s0-ddp"):
        c = runs[name]
        assert c.n_algo == 5 and c.epochs == 3000 and c.horizon == 16 and c.rollout.t_a == 4 and c.rollout.single_shooting
        assert list(c.rollout.eval_t_a_last) == [t for t in range(1, 16) if t != 4]
    assert runs["double_pendulum-pddp_s-n30-s4"].rollout.eval_t_a_last == ()
    params = tmp_path / "params.yaml"
    params.write_text("experiment: small\nexperiment_stages: {group: {}}\n")   # as written before version 2
    counts = select_experiment("fig2", params_path=params, root=ROOT)
    written = yaml.safe_load(params.read_text())
    assert written["experiment"] == "fig2" and counts == {"runs": 40}
    assert set(written) == {"experiment"}       # the settings stay in pipelines/fig2.yaml (DVC parameters)
    with pytest.raises(SdpError, match="unknown experiment 'fig9'; known: .*fig2"):
        select_experiment("fig9", params_path=params, root=ROOT)


def test_per_iteration_trajectory_schedules():
    """Fig. 3 and Fig. 4's loops grow their datasets: n_traj_schedule gives the count per iteration."""
    fig4 = loop_configs("fig4", load_experiment("fig4", root=ROOT))
    q9 = fig4["quadrotor-9-sdp-n30-s0"]
    assert q9.n_traj == (30, 50, 70, 90, 100) and [q9.n_traj_at(k) for k in range(5)] == [30, 50, 70, 90, 100]
    fig3 = loop_configs("fig3", load_experiment("fig3", root=ROOT))
    assert fig3["ur5-rinit-rtgt-sdp-n100-s0-h64-ta63"].n_traj == (100, 100, 100, 200, 200)
    assert {(c.horizon, c.rollout.t_a) for c in fig3.values()} == {(32, 16), (32, 31), (64, 16), (64, 31), (64, 63)}


def test_bad_experiment_files_are_one_clear_error(tmp_path):
    (tmp_path / "pipelines").mkdir()
    cases = {"keys": "groups: [{task: pendulum, epoch: 3}]\n",
             "train": "groups: [{task: pendulum, train: {batchsize: 3}}]\n",
             "twice": "groups: [{task: pendulum}, {task: pendulum}]\n",
             "top": "runner: stages\ngroups: [{task: pendulum}]\n",
             "ta": "groups: [{task: pendulum, horizon: 8, t_a: 9}]\n",
             "both": "groups: [{task: pendulum, n_traj: [3], n_traj_schedule: [3, 5]}]\n",
             "sched": "groups: [{task: pendulum, n_traj_schedule: [3, 0]}]\n"}
    msgs = {"keys": "unknown keys \\['epoch'\\]", "train": "unknown train option", "twice": "appears in two groups",
            "top": "unknown keys \\['runner'\\]", "ta": "t_a \\[9\\] outside",
            "both": "not both", "sched": "list of positive integers"}
    for name, text in cases.items():
        (tmp_path / "pipelines" / f"{name}.yaml").write_text(text)
        with pytest.raises(SdpError, match=msgs[name]):
            loop_configs(name, load_experiment(name, root=tmp_path))


def test_version_and_pipeline_help_list_what_exists():
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.data.artifacts import git_revision

    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.startswith("sdp 0.") and git_revision().split("+")[0][:7] in r.output
    r = CliRunner().invoke(app, ["pipeline", "--help"], terminal_width=200)
    from pathlib import Path

    names = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "pipelines").glob("*.yaml"))
    text = " ".join(r.output.replace("│", " ").split())     # (rich may wrap the help inside its box)
    assert r.exit_code == 0 and f"({', '.join(names)} here)" in text


def test_committed_estimates_read_back_to_their_printed_totals():
    """Every saved estimate under results/estimates/ parses to as many runs as its header line says, and its
    per-run hours add up to the printed one-process total."""
    import re

    from sdp_cli.report.estimates import read_estimate

    files = sorted((ROOT / "results" / "estimates").glob("*.txt"))
    assert files
    for f in files:
        text = f.read_text()
        runs = int(re.search(r"estimate for '\w+': (\d+) runs", text).group(1))
        total = float(re.search(r"total on cpu: ([\d.]+) h in one process", text).group(1))
        df = read_estimate(f)
        assert len(df) == runs and df.run.is_unique, f
        assert df.total_cpu_h.sum() == pytest.approx(total, abs=1e-3 * runs + 0.01), f


def test_estimate_counts_the_papers_epochs_and_writes_nothing(tmp_path, monkeypatch):
    """small: 10 pendulum trajectories, T_h 16 -> E = ceil(10 * 84 / 16) = 53 chunks, one step of 53 per
    epoch; fig2: 30 double-pendulum trajectories -> E = 158 at B = 256."""
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.experiments.estimate import estimate, training_stages

    small = training_stages(loop_configs("small", load_experiment("small", root=ROOT)))
    assert len(small) == 4 and {(s.E, s.B) for s in small} == {(53, 53)}
    assert all(s.steps == s.epochs for s in small)
    fig2 = training_stages(loop_configs("fig2", load_experiment("fig2", root=ROOT)))
    assert {(s.E, s.B) for s in fig2 if s.method in ("sdp", "dp")} == {(158, 158)}
    df, totals = estimate("small", workers=2, budget_s=4, root=ROOT)
    assert list(df.run) == ["pendulum-sdp-n10-s0", "pendulum-dp-n10-s0"]
    assert list(df.steps) == [2 * 700, 2 * 700] and list(df.samples) == [2 * 700 * 53] * 2
    assert (df.train_cpu_s > 0).all() and (df.to_s > 0).all()
    assert "stack" not in df   # SDP and DP do not share a stack (a DP member would pay SDP's tangent pass)
    t = totals["cpu"]
    assert t["parallel_s"] == pytest.approx(max(t["sequential_s"] / 2, float(df.total_cpu_s.max())))
    # saved as results/estimates/ keeps it, the reports read it back (hours printed to 3 decimals)
    from sdp_cli.experiments.estimate import format_estimate
    from sdp_cli.report.estimates import estimated_hours, read_estimate

    saved = tmp_path / "small.txt"
    saved.write_text("# 2026-11-26T20:00:00Z load 1.0\n" + format_estimate("small", df, totals) + "\n")
    back = read_estimate(saved)
    assert list(back.run) == list(df.run) and list(back.steps) == list(df.steps)
    assert back.total_cpu_h.to_numpy() == pytest.approx(df.total_cpu_s.to_numpy() / 3600, abs=6e-4)
    assert estimated_hours(saved) == dict(zip(back.run, back.total_cpu_h))
    assert read_estimate(tmp_path / "missing.txt").empty and estimated_hours(tmp_path / "missing.txt") == {}
    # the CLI writes nothing (params.yaml untouched) and prints the totals
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "small.yaml").write_text((ROOT / "pipelines" / "small.yaml").read_text())
    before = sorted(p.name for p in tmp_path.rglob("*"))
    r = CliRunner().invoke(app, ["pipeline", "small", "--estimate", "--workers", "3"])
    assert r.exit_code == 0, r.output
    assert "with 3 parallel workers" in r.output and sorted(p.name for p in tmp_path.rglob("*")) == before


def test_estimate_measures_every_step_on_one_thread(monkeypatch):
    """The stacks' calibration ran after the estimate had restored the process's threads: beside two training
    runs on 2 cores, a stack of 3 pendulum runs measured 6.7 s a step (0.1 s on one thread) and ablation_k came
    out at 11 h. Every measurement runs on one thread, as the runs train; the threads are put back after."""
    import torch

    from sdp_cli.experiments import estimate as E

    seen = []

    def fake(*a, **kw):
        seen.append(torch.get_num_threads())
        return 0.01

    monkeypatch.setattr(E, "step_seconds", fake)
    monkeypatch.setattr(E, "stacked_step_seconds", fake)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        df, _ = E.estimate("ablation_k", budget_s=1, root=ROOT)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert (df["stack"] == 3).all() and seen == [1, 1]     # the solo calibration, then the stacks'


def test_estimate_times_a_loops_to_by_its_family(monkeypatch):
    """`--estimate` charges a loop's TO at its family's reference time: box-FDDP's where the task gives one
    (results/tasks/TO_alone.md), multiple shooting's otherwise (a user's task); single shooting's either way."""
    from sdp_cli.experiments import estimate
    from sdp_cli.experiments.estimate import to_reference

    assert to_reference("double_pendulum") == (0.010, 0.155)
    assert to_reference("double_pendulum", "ddp") == (0.045, 0.155)
    assert to_reference("ur5-fixed", "ddp")[0] > to_reference("ur5-fixed")[0]
    assert to_reference("quadrotor-9", "ddp") == (7.4, 120.0)      # the augmented-Lagrangian DDP: 12x fatrop's
    real = estimate.get_task

    def without_ddp_time(name, **kw):
        t = real(name, **kw)
        t.reference_ddp_s = None
        return t

    monkeypatch.setattr(estimate, "get_task", without_ddp_time)
    assert to_reference("quadrotor-9", "ddp") == to_reference("quadrotor-9") == (0.63, 120.0)   # fatrop's


def test_estimate_times_steps_in_cpu_time_not_wall_time():
    """A step that waits (as one does on a loaded machine, descheduled) costs its CPU time: the calibration read
    5-11x high in wall time beside training runs (fig3: 1598 h in one call, 147 h in another)."""
    import time

    from sdp_cli.experiments.estimate import _median_seconds

    def waits():
        time.sleep(0.02)

    def works():
        t0 = time.thread_time()
        while time.thread_time() - t0 < 0.02:
            pass

    assert _median_seconds(waits, 0.1) < 0.005
    assert _median_seconds(works, 0.1) >= 0.019


def test_estimate_only_estimates_the_runs_named(monkeypatch):
    """`sdp pipeline NAME --estimate --only a,b` estimates those runs (stacked among themselves), not all of them;
    an unknown name is one error line, as with --run."""
    import pandas as pd

    from sdp_cli.experiments import estimate as E

    seen = {}

    def fake(runs, train, devices, workers, budget_s, log, stack):
        seen["runs"] = sorted(runs)
        return pd.DataFrame(), {}

    monkeypatch.setattr(E, "_estimate", fake)
    E.estimate("small", only=["pendulum-sdp-n10-s0"])
    assert seen["runs"] == ["pendulum-sdp-n10-s0"]
    with pytest.raises(SdpError, match="has no run nope"):
        E.estimate("small", only=["nope"])

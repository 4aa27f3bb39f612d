"""Experiment files (pipelines/*.yaml) expand into DVC stage lists that chain correctly."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sdp_cli.errors import SdpError
from sdp_cli.pipeline import expand, load_experiment, select_experiment
from sdp_cli.tasks import task_names

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "pipelines").glob("*.yaml"))


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_expands_into_chained_stages(name):
    spec = load_experiment(name, root=ROOT)
    if spec.get("runner") == "group":   # one stage runs every run (sdp_cli.runner); its per-step view must chain too
        grouped = expand(name, spec)
        assert list(grouped["group"]) == [name] and not grouped["train_first"]
    stages = expand(name, spec, per_step=True)
    assert stages["train_first"], name
    trained = {v["dir"] + "/policy" for k in ("train_first", "train_next") for v in stages[k].values()}
    for key, st in list(stages["collect_next"].items()) + list(stages["train_next"].items()):
        assert st["prev"] in trained, (key, st["prev"])       # each iteration names its predecessor
        assert st["prev"] != st["dir"] + "/policy"
    collected = {v["dir"] + "/data.npz" for k in ("collect_first", "collect_next") for v in stages[k].values()}
    assert all(st["data"] in collected for k in ("train_first", "train_next") for st in stages[k].values())
    assert all(st["policy"] in trained for st in stages["evaluate"].values())
    assert {st["task"] for k in ("collect_first", "collect_next") for st in stages[k].values()} <= set(task_names())


def test_fig2_stage_counts_and_selection(tmp_path):
    stages = expand("fig2", load_experiment("fig2", root=ROOT))
    # 2 methods x (4 iterations at T_a = 4, then 15 T_a values at the last one)
    assert len(stages["evaluate"]) == 2 * (4 + 15)
    assert len(stages["collect_first"]) == 1                 # the naive-guess dataset is shared
    assert len(stages["train_next"]) == len(stages["collect_next"]) == 2 * 4
    params = tmp_path / "params.yaml"
    params.write_text("experiment: small\n")
    counts = select_experiment("fig2", params_path=params, root=ROOT)
    written = yaml.safe_load(params.read_text())
    assert written["experiment"] == "fig2" and counts["evaluate"] == 38
    with pytest.raises(SdpError, match="unknown experiment 'fig9'; known: .*fig2"):
        select_experiment("fig9", params_path=params, root=ROOT)


def test_version_and_pipeline_help_list_what_exists():
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.data.artifacts import git_revision

    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.startswith("sdp 0.") and git_revision().split("+")[0][:7] in r.output
    r = CliRunner().invoke(app, ["pipeline", "--help"], terminal_width=200)
    from pathlib import Path

    names = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "pipelines").glob("*.yaml"))
    assert r.exit_code == 0 and f"({', '.join(names)} here)" in " ".join(r.output.split())


def test_estimate_counts_the_papers_epochs_and_writes_nothing(tmp_path, monkeypatch):
    """small: 10 pendulum trajectories, T_h 16 -> E = ceil(10 * 84 / 16) = 53 chunks, one step of 53 per
    epoch; fig2: 30 double-pendulum trajectories -> E = 158 at B = 256."""
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.estimate import estimate, training_stages

    small = training_stages(expand("small", load_experiment("small", root=ROOT)))
    assert len(small) == 4 and {(s.E, s.B) for s in small} == {(53, 53)}
    assert all(s.steps == s.epochs for s in small)
    fig2 = training_stages(expand("fig2", load_experiment("fig2", root=ROOT)))
    assert {(s.E, s.B) for s in fig2 if s.method in ("sdp", "dp")} == {(158, 158)}
    df, totals = estimate("small", workers=2, budget_s=4, root=ROOT)
    assert list(df.run) == ["pendulum-sdp-n10-s0", "pendulum-dp-n10-s0"]
    assert list(df.steps) == [2 * 700, 2 * 700] and list(df.samples) == [2 * 700 * 53] * 2
    assert (df.train_cpu_s > 0).all() and (df.to_s > 0).all()
    t = totals["cpu"]
    assert t["parallel_s"] == pytest.approx(max(t["sequential_s"] / 2, float(df.total_cpu_s.max())))
    # the CLI writes nothing (params.yaml untouched) and prints the totals
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "small.yaml").write_text((ROOT / "pipelines" / "small.yaml").read_text())
    before = sorted(p.name for p in tmp_path.rglob("*"))
    r = CliRunner().invoke(app, ["pipeline", "small", "--estimate", "--workers", "3"])
    assert r.exit_code == 0, r.output
    assert "with 3 parallel workers" in r.output and sorted(p.name for p in tmp_path.rglob("*")) == before

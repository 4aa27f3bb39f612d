"""The results/ top index written by `sdp report` next to each experiment folder."""

from __future__ import annotations

import pytest

from sdp_cli.report.make import _top_index


def test_top_index_lists_each_experiment_with_its_commit(tmp_path):
    results = tmp_path / "results"
    for name, commit in (("small", "abc123"), ("fig2", "def456")):
        (results / name).mkdir(parents=True)
        (results / name / "README.md").write_text(
            f"# Results: {name}\n\nProduced by `sdp report --runs runs/{name} --out results/{name}` at commit `{commit}`\n")
        (results / name / "all_runs.csv").write_text("a\n1\n")
    (results / "stray").mkdir()  # no README: not an experiment folder
    text = _top_index(results).read_text()
    assert "| [fig2](fig2/README.md) | `def456` | 1 |" in text
    assert "| [small](small/README.md) | `abc123` | 1 |" in text
    assert "stray" not in text
    assert text.index("fig2") < text.index("small")


def test_report_ignores_runs_the_selected_experiment_no_longer_has(tmp_path, monkeypatch):
    """The DVC output runs/<experiment> persists across re-runs, so folders of runs the experiment file no
    longer has (e.g. an earlier n_traj sweep) stay: for the experiment params.yaml selects, only its
    current runs are reported."""
    import pandas as pd
    import pytest
    import yaml

    from sdp_cli.errors import SdpError
    from sdp_cli.algorithm.evaluate import write_evaluation
    from sdp_cli.report.make import make_report

    monkeypatch.chdir(tmp_path)
    row = {"task": "pendulum", "method": "sdp", "t_a": 8, "k_rollout": 5, "train_seed": 0, "epochs": 700,
           "test_seed": 0, "n": 20, "policy_cost_mean": 0.0, "policy_cost_median": 0.0, "success_rate": 0.5,
           "rollout_time": 1.0, "diverged": 0, "iteration": 0}
    for n_traj, cost in ((5, 50.0), (10, 20.0)):
        run = f"pendulum-sdp-n{n_traj}-s0"
        d = tmp_path / "runs" / "exp" / run / "it0" / "eval"
        d.mkdir(parents=True)
        write_evaluation([{**row, "n_traj": n_traj, "run": run, "policy_cost_mean": cost}], d / "eval.csv",
                         [{"rollouts": None, "refined": None, "policy": None, "data": None}])
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "exp.yaml").write_text("groups: [{task: pendulum, methods: [sdp], n_traj: [10]}]\n")
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"experiment": "exp"}))
    logs = []
    make_report("runs/exp", "results/exp", "exp", log=logs.append)
    rows = pd.read_csv(tmp_path / "results" / "exp" / "all_runs.csv")
    assert list(rows.n_traj) == [10] and list(rows.policy_cost_mean) == [20.0]
    assert any("ignoring 1 evaluation" in s for s in logs)
    # another experiment selected: everything under --runs is reported (sdp loop folders, old runs)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"experiment": "small"}))
    make_report("runs/exp", "results/exp", "exp")
    assert sorted(pd.read_csv(tmp_path / "results" / "exp" / "all_runs.csv").n_traj) == [5, 10]
    (tmp_path / "pipelines" / "exp.yaml").write_text("groups: [{task: pendulum, methods: [dp]}]\n")
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"experiment": "exp"}))
    with pytest.raises(SdpError, match="no evaluation of the current experiment"):
        make_report("runs/exp", "results/exp", "exp")


def test_report_reads_only_what_manifests_name(tmp_path, monkeypatch):
    """An eval.csv without its manifest is not read (logged); a manifest that does not match its CSV is
    one clear error; rows take run, iteration and paths from the manifest, not from the folder names."""
    import json

    import pandas as pd
    import pytest

    from sdp_cli.errors import SdpError
    from sdp_cli.algorithm.evaluate import manifest_path, write_evaluation
    from sdp_cli.report.runs import load_runs

    monkeypatch.chdir(tmp_path)
    row = {"task": "pendulum", "method": "dp", "n_traj": 3, "t_a": 4, "train_seed": 1, "n": 2, "epochs": 5,
           "policy_cost_mean": 1.0, "policy_cost_median": 1.0, "success_rate": 1.0, "rollout_time": 0.5,
           "run": "my-run", "iteration": 3, "controls_violation_rate": 0.0,
           "terminal_cost_mean": 0.0}   # (a row of this code: no rollout re-read)
    d = tmp_path / "runs" / "anywhere" / "deep"      # no it<k> folder: nothing is guessed from the path
    d.mkdir(parents=True)
    ro = d / "r.npz"
    ro.write_bytes(b"x")
    write_evaluation([row], d / "eval.csv", [{"rollouts": str(ro), "refined": None, "policy": None, "data": None}])
    (tmp_path / "runs" / "old").mkdir()
    pd.DataFrame([row]).to_csv(tmp_path / "runs" / "old" / "eval.csv", index=False)   # no manifest
    logs = []
    df = load_runs(tmp_path / "runs", log=logs.append)
    assert len(df) == 1 and df.run.iloc[0] == "my-run" and df.iteration.iloc[0] == 3
    assert df.rollouts.iloc[0] == str(ro.resolve()) and df.refined.isna().all()
    assert df.rollout_time.iloc[0] == 0.5                 # joined back from the timing sidecar
    assert any("1 eval.csv file(s)" in s and "without a manifest" in s for s in logs)
    man = json.loads(manifest_path(d / "eval.csv").read_text())
    assert man["entries"][0]["rollouts"] == "r.npz"       # relative: the runs folder can move
    man["entries"].append(man["entries"][0])
    manifest_path(d / "eval.csv").write_text(json.dumps(man))
    with pytest.raises(SdpError, match="describes 2 rows but .* has 1"):
        load_runs(tmp_path / "runs")


def test_runs_in_symlinked_folders_are_read_once_each(tmp_path):
    """A runs folder assembled with ``ln -s`` is read whole: a linked run counts once however many links
    reach it, a link to an ancestor does not loop, and `sdp migrate` walks the same folders."""
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.algorithm.evaluate import write_evaluation
    from sdp_cli.report.runs import load_runs

    row = {"task": "pendulum", "method": "dp", "n_traj": 3, "t_a": 4, "train_seed": 0, "n": 2, "epochs": 5,
           "policy_cost_mean": 1.0, "success_rate": 1.0, "controls_violation_rate": 0.0, "terminal_cost_mean": 0.0}
    runs, elsewhere = tmp_path / "runs", tmp_path / "elsewhere"
    for d, name in ((runs / "here" / "eval", "here"), (elsewhere / "there" / "it1" / "eval", "there")):
        d.mkdir(parents=True)
        write_evaluation([{**row, "run": name, "iteration": 1}], d / "eval.csv", [{"rollouts": None}])
    (runs / "there").symlink_to(elsewhere / "there", target_is_directory=True)
    (runs / "there-again").symlink_to(elsewhere / "there", target_is_directory=True)
    (runs / "here" / "up").symlink_to(runs, target_is_directory=True)          # a loop back to the top
    df = load_runs(runs)
    assert sorted(df.run) == ["here", "there"]
    r = CliRunner().invoke(app, ["migrate", str(runs)])
    assert r.exit_code == 0 and "2 already current" in r.output, r.output


def test_rows_evaluated_before_policy_ties_are_recounted_from_their_refine(tmp_path):
    """Old eval.csv rows counted a shared optimum as a policy win; the report recounts them."""
    import numpy as np
    import pandas as pd

    from sdp_cli.migrate import migrate_rows

    refined = tmp_path / "refined.npz"
    np.savez(refined, inst_winner=np.array([0, 0, 1]), inst_pol_cost=np.array([2.5, 1.0, 3.0]),
             inst_base_cost=np.array([2.5, 2.0, 2.0]), inst_base_converged=np.array([True, True, True]))
    old = pd.DataFrame({"policy_wins": [2, 5], "refined": [str(refined), None]})
    got = migrate_rows(old)
    assert got.loc[0, "policy_wins"] == 1 and got.loc[0, "policy_ties"] == 1
    assert np.isnan(got.loc[1, "policy_wins"]) and np.isnan(got.loc[1, "policy_ties"])   # no refine: unknown
    new = pd.DataFrame({"policy_wins": [4], "policy_ties": [1], "refined": [str(refined)]})
    pd.testing.assert_frame_equal(migrate_rows(new), new)                          # new rows kept as is


def test_rows_evaluated_before_violation_groups_get_them_from_their_rollouts(tmp_path):
    """Per-group violation rates and the terminal cost's mean, recomputed from an older rollout's X, U and xi,
    are what this code's rollout evaluation stores; rows of this code are kept as they are."""
    import numpy as np
    import pandas as pd

    from sdp_cli.data.artifacts import save_npz
    from sdp_cli.algorithm.evaluate import evaluation_row
    from sdp_cli.migrate import migrate_rows
    from sdp_cli.algorithm.rollout import evaluate_rollouts
    from sdp_cli.tasks import get_task

    X, U = np.zeros((2, 101, 2)), np.zeros((2, 100, 1))
    X[1, -1, 0] = 1.0                                                # one ends at the goal (q = 0), one 1 rad away
    U[1, 7] = 30.0                                                   # above the pendulum's 25 N m bound
    xis = np.zeros((2, 2))
    ro = save_npz(tmp_path / "r.npz", {"X": X, "U": U, "xi": xis, "cost": np.zeros(2)},
                  kind="rollout", config={}, task="pendulum", task_options={})
    old = pd.DataFrame({"violation_rate": [0.5, 0.0], "rollouts": [str(ro), None]})
    got = migrate_rows(old)
    assert got.loc[0, "controls_violation_rate"] == 0.5 and np.isnan(got.loc[1, "controls_violation_rate"])
    ev = evaluate_rollouts(get_task("pendulum"), X, U, xis)
    assert ev["terminal_cost"][0] < 1e-12 < ev["terminal_cost"][1] < ev["cost"][1]
    assert got.loc[0, "terminal_cost_mean"] == np.mean(ev["terminal_cost"]) and np.isnan(got.loc[1, "terminal_cost_mean"])
    now = save_npz(tmp_path / "now.npz", {**ev, "X": X, "U": U, "xi": xis}, kind="rollout", config={},
                   task="pendulum", task_options={})
    assert evaluation_row(now)["terminal_cost_mean"] == got.loc[0, "terminal_cost_mean"]
    ev["terminal_cost"][1] = np.inf                                  # a diverged rollout: the mean is inf
    diverged = save_npz(tmp_path / "div.npz", ev, kind="rollout", config={}, task="pendulum", task_options={})
    assert evaluation_row(diverged)["terminal_cost_mean"] == np.inf
    new = old.assign(controls_violation_rate=[0.25, 0.0], terminal_cost_mean=[3.0, 1.0])
    pd.testing.assert_frame_equal(migrate_rows(new), new)   # rows of this code are kept as they are


def test_fig3_runs_are_drawn_apart_per_horizon_and_action_length():
    """Fig. 3 runs one loop per (T_h, T_a) and method: the figures must not average them together. Each run
    becomes the variant ``<method>-h<T_h>-ta<T_a>`` (T_a the loop's, evaluated at its first iteration),
    while Fig. 2's T_a sweep at the last iteration of one loop stays one method; each run keeps its rows."""
    import matplotlib.colors as mc
    import numpy as np
    import pandas as pd

    from sdp_cli.report.rows import loop_t_a as _loop_t_a
    from sdp_cli.report.figures.style import COLORS, MARKERS, method_order
    from sdp_cli.report.rows import Variant, method_label
    from sdp_cli.report.rows import method_variants

    rows = []
    for (h, t_a), its in (((32, 16), (0, 1)), ((64, 63), (0,))):  # Fig. 3: two loops of SDP, seed 0, one unfinished
        for it in its:
            rows.append({"task": "ur5-rinit", "method": "sdp", "horizon": h, "t_a": t_a, "train_seed": 0,
                         "iteration": it, "run": f"ur5-rinit-sdp-n50-s0-h{h}-ta{t_a}"})
    for it, t_as in ((0, [4]), (1, [4, 1, 9, 15])):          # Fig. 2: one loop, T_a sweep at the last iteration
        rows += [{"task": "double_pendulum", "method": "sdp", "horizon": 16, "t_a": t, "train_seed": 0,
                  "iteration": it, "run": "double_pendulum-sdp-n30-s0"} for t in t_as]
    df = pd.DataFrame(rows)
    v = method_variants(df)
    assert sorted(set(v[v.task == "ur5-rinit"].method)) == ["sdp-h32-ta16", "sdp-h64-ta63"]
    assert {m.pair for m in v[v.task == "ur5-rinit"].method} == {(32, 16), (64, 63)}   # typed, not parsed
    assert set(v[v.task == "double_pendulum"].method) == {"sdp"}
    assert set(df.method) == {"sdp"}                          # the input (all_runs.csv) keeps the plain method
    # both loops keep their rows (grouped per run; per method and seed, the unfinished loop's T_a 63 is
    # missing at iteration 1, so its rows were dropped)
    kept = _loop_t_a(df[df.task == "ur5-rinit"])
    assert sorted(kept.t_a) == [16, 16, 63]
    assert list(_loop_t_a(df[df.task == "double_pendulum"]).t_a) == [4, 4]
    # one hue per method, five distinct shades for Fig. 3's five pairs, the method's marker
    pairs = [(32, 16), (32, 31), (64, 16), (64, 31), (64, 63)]
    shades = [mc.to_rgb(COLORS.get(Variant("sdp", pair=p))) for p in pairs]
    assert len(set(shades)) == 5 and MARKERS.get(Variant("dp", pair=(64, 63))) == "s"
    red = np.array(mc.to_rgb("tab:red"))
    assert all(np.argmax(s) == np.argmax(red) for s in shades)
    assert sorted([Variant("sdp", pair=p) for p in reversed(pairs)], key=method_order) == [
        f"sdp-h{h}-ta{t}" for h, t in pairs]
    # within one figure the pairs drawn spread from dark to light, whatever their values
    few = [Variant("sdp", pair=(8, 4)), Variant("sdp", pair=(16, 8))]
    dark, light = (np.array(mc.to_rgb(COLORS.get(m, among=few))) for m in few)
    assert dark.sum() < red.sum() < light.sum()
    assert method_label(Variant("sdp", pair=(64, 63))) == "SDP (T_h 64, T_a 63)"
    assert method_label(Variant("pddp_s", k=2)) == "PDDP+S-K2"
    assert method_label(Variant("pddp_s", pair=(32, 16))) == "PDDP+S (T_h 32, T_a 16)"  # the paper's name, not PDDP_S
    # the parts are typed, never parsed from the key: a method whose name looks like a variant stays itself
    odd = Variant("chunk-K9", k=2)
    assert odd == "chunk-K9-K2" and odd.method == "chunk-K9" and odd.k == 2 and method_label("chunk-K9") == "CHUNK-K9"
    assert method_order(odd) == ("chunk-K9", (2,)) and Variant("dp", pair=(8, 4)).replace(pair=None) == "dp"


def test_loop_figures_use_one_budget_per_method():
    """fig2a/fig2b/table2c/traj/loop average over seeds: on Fig. 1's sweeps they take, per task and method, the runs
    with the most epochs and the largest dataset (else one point would average 2 x 2 budgets and call them seeds);
    a loop whose n_traj grows over its iterations (Fig. 3's schedule) keeps every iteration."""
    import pandas as pd

    from sdp_cli.report.figures.paper import budget_title
    from sdp_cli.report.rows import largest_budget

    rows = []
    for method, epochs_all in (("pddp", (1000, 2000)), ("pddp_s", (1000, 2000, 3000))):   # Fig. 1a: PDDP+S has 3e3
        for epochs in epochs_all:      # one run per size and seed, evaluated at each epoch count (a row per count)
            for n in (2, 16):
                for seed in (0, 1):
                    rows.append({"task": "ur5-fixed", "method": method, "epochs": epochs, "n_traj": n, "train_seed": seed,
                                 "iteration": 0, "run": f"ur5-fixed-{method}-n{n}-s{seed}"})
    for it, n in enumerate((50, 50, 100)):                                                # Fig. 3: a schedule
        rows.append({"task": "ur5-rinit", "method": "sdp", "epochs": 10000, "n_traj": n, "train_seed": 0,
                     "iteration": it, "run": "ur5-rinit-sdp-n50-s0"})
    df = pd.DataFrame(rows)
    kept = largest_budget(df)
    u = kept[kept.task == "ur5-fixed"]
    assert set(zip(u.method, u.epochs, u.n_traj)) == {("pddp", 2000, 16), ("pddp_s", 3000, 16)}
    assert len(u) == 4                                                # both seeds of each
    assert list(kept[kept.task == "ur5-rinit"].n_traj) == [50, 50, 100]
    assert budget_title(u) == ", largest budget per method"
    assert budget_title(u[u.method == "pddp"]) == ", n_traj 16, 2000 epochs"
    assert budget_title(kept[kept.task == "ur5-rinit"]) == ", n_traj 50, 50, 100 by iteration, 10000 epochs"
    assert budget_title(kept[(kept.task == "ur5-rinit") & (kept.iteration < 2)]) == ", n_traj 50, 10000 epochs"


def test_report_readme_says_how_much_of_the_experiment_it_holds(tmp_path):
    """Per group of the experiment file: runs finished (last iteration at the group's epochs; those of an older
    results version counted apart), partway (named, with iterations or epochs so far) and not run; one line
    once every run finished at the current results version."""
    import pandas as pd
    import yaml

    from sdp_cli import RESULTS_VERSION
    from sdp_cli.report.coverage import coverage_lines, experiment_coverage

    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "x.yaml").write_text(yaml.safe_dump({"groups": [
        {"task": "ur5-rinit", "methods": ["sdp", "dp"], "n_traj_schedule": [50, 50, 100], "n_algo": 3,
         "epochs": 100, "tag": "h64-ta63"},
        {"task": "pendulum", "methods": ["sdp"], "seeds": [0, 1], "n_traj": [1, 3], "epochs": 2000}]}))
    rows = [{"run": "ur5-rinit-sdp-n50-s0-h64-ta63", "iteration": it, "epochs": 100} for it in range(3)]
    rows += [{"run": "ur5-rinit-dp-n50-s0-h64-ta63", "iteration": it, "epochs": 100} for it in range(2)]
    rows += [{"run": "pendulum-sdp-n1-s0", "iteration": 0, "epochs": e} for e in (1000, 2000)]
    rows += [{"run": "pendulum-sdp-n3-s1", "iteration": 0, "epochs": 1000}]          # its save_at checkpoint only
    rows += [{"run": "elsewhere-sdp-n1-s0", "iteration": 0, "epochs": 5}]             # not a run of the experiment
    cov = experiment_coverage(pd.DataFrame(rows), "x", tmp_path)
    assert cov.not_run_h.isna().all()                                 # no estimate given
    assert cov.drop(columns=["not_run_h", "older_h"]).to_dict("records") == [
        {"group": "ur5-rinit sdp, dp h64-ta63", "runs": 2, "finished": 1, "older": 0, "older_partway": 0,
         "partway": "1 (ur5-rinit-dp-n50-s0-h64-ta63 2/3)", "not_run": 0},
        {"group": "pendulum sdp, 2000 epochs", "runs": 4, "finished": 1, "older": 0, "older_partway": 0,
         "partway": "1 (pendulum-sdp-n3-s1 1000/2000 epochs)", "not_run": 2}]
    lines = coverage_lines(pd.DataFrame(rows), "x", tmp_path)
    assert "## Runs of `pipelines/x.yaml` in this report: 2 of 6 finished" in lines
    assert "| pendulum sdp, 2000 epochs | 4 | 1 | 1 (pendulum-sdp-n3-s1 1000/2000 epochs) | 2 |" in lines
    # with a saved --estimate: the runs not run carry their hours (pendulum-sdp-n1-s1 and -n3-s0; the partway
    # and finished runs' hours are not counted)
    hours = {"pendulum-sdp-n1-s1": 1.25, "pendulum-sdp-n3-s0": 2.5, "pendulum-sdp-n3-s1": 9.0, "pendulum-sdp-n1-s0": 9.0}
    lines = coverage_lines(pd.DataFrame(rows), "x", tmp_path, hours=hours, hours_from="../estimates/x.txt")
    assert "| pendulum sdp, 2000 epochs | 4 | 1 | 1 (pendulum-sdp-n3-s1 1000/2000 epochs) | 2 (3.8 h) |" in lines
    assert "| ur5-rinit sdp, dp h64-ta63 | 2 | 1 | 1 (ur5-rinit-dp-n50-s0-h64-ta63 2/3) | 0 |" in lines
    assert any("as saved in `../estimates/x.txt`" in ln for ln in lines)
    done = [{"run": r, "iteration": it, "epochs": e} for r, n, e in (
        ("ur5-rinit-sdp-n50-s0-h64-ta63", 3, 100), ("ur5-rinit-dp-n50-s0-h64-ta63", 3, 100),
        ("pendulum-sdp-n1-s0", 1, 2000), ("pendulum-sdp-n3-s0", 1, 2000), ("pendulum-sdp-n1-s1", 1, 2000),
        ("pendulum-sdp-n3-s1", 1, 2000)) for it in range(n)]
    # every run finished at the code's results version (or of none recorded): one line says so
    assert coverage_lines(pd.DataFrame(done), "x", tmp_path) == [
        "", f"## Runs of `pipelines/x.yaml` in this report: all 6 finished, none of an older results version than {RESULTS_VERSION}"]
    # every run finished, two of them by code of an older results version: still to be re-made, and said so
    old = pd.DataFrame(done).assign(results_version=RESULTS_VERSION)
    old.loc[old.run.isin(["pendulum-sdp-n1-s0", "pendulum-sdp-n3-s0"]), "results_version"] = 1
    old.loc[old.run == "ur5-rinit-sdp-n50-s0-h64-ta63", "results_version"] = float("nan")   # unknown: not counted
    assert experiment_coverage(old, "x", tmp_path).older.tolist() == [0, 2]
    lines = coverage_lines(old, "x", tmp_path)
    assert f"## Runs of `pipelines/x.yaml` in this report: 6 of 6 finished, 2 of them of an older results version than {RESULTS_VERSION}" in lines
    assert "| pendulum sdp, 2000 epochs | 4 | 4 (2 of an older results version) | 0 | 0 |" in lines
    assert "| ur5-rinit sdp, dp h64-ta63 | 2 | 2 | 0 | 0 |" in lines
    # with a saved --estimate, the hours of re-making the older runs (n1-s0 9.0 h and n3-s0 2.5 h)
    lines = coverage_lines(old, "x", tmp_path, hours=hours, hours_from="../estimates/x.txt")
    assert "| pendulum sdp, 2000 epochs | 4 | 4 (2 of an older results version, 11.5 h to re-make) | 0 | 0 |" in lines
    # a partway run of an older results version names it (it will be re-made, not resumed), and the README
    # says what "older" means even when no finished run is older
    part = pd.DataFrame(rows).assign(results_version=RESULTS_VERSION)
    part.loc[part.run == "ur5-rinit-dp-n50-s0-h64-ta63", "results_version"] = 1
    lines = coverage_lines(part, "x", tmp_path)
    assert "| ur5-rinit sdp, dp h64-ta63 | 2 | 1 | 1 (ur5-rinit-dp-n50-s0-h64-ta63 2/3 of results version 1) | 0 |" in lines
    assert "## Runs of `pipelines/x.yaml` in this report: 2 of 6 finished" in lines
    assert any("Older results version: evaluated by code" in ln for ln in lines)
    lines = coverage_lines(part, "x", tmp_path, hours={"ur5-rinit-dp-n50-s0-h64-ta63": 5.5}, hours_from="e.txt")
    assert ("| ur5-rinit sdp, dp h64-ta63 | 2 | 1 | 1 (ur5-rinit-dp-n50-s0-h64-ta63 2/3 of results version 1; 5.5 h to "
            "re-make) | 0 |") in lines


def test_evaluations_of_older_code_are_refused_until_migrated_once(tmp_path):
    """`sdp report` refuses format-1 evaluations in one line naming `sdp migrate`; the migration adds what this
    code computes (a loop's ``n_algo`` from ``<run>/loop_config.json``, the evaluation's folder being
    ``<run>/it<k>/eval``; rows of no loop stay without it; each entry's ``git_rev``), keeps the old files as
    ``*.v1`` and its other values as they were, and migrating again changes nothing."""
    import json

    import pandas as pd
    import pytest
    from typer.testing import CliRunner

    from sdp_cli.cli import app
    from sdp_cli.errors import SdpError
    from sdp_cli.algorithm.evaluate import LAYOUT, manifest_path, write_evaluation
    from sdp_cli.migrate import migrate_evaluation
    from sdp_cli.report.runs import load_runs

    row = {"task": "pendulum", "method": "dp", "n_traj": 3, "t_a": 4, "train_seed": 1, "n": 2, "epochs": 5,
           "policy_cost_mean": 1.5, "success_rate": 1.0, "controls_violation_rate": 0.0, "terminal_cost_mean": 0.25}
    runs = tmp_path / "runs"
    loop_eval, lone = runs / "quadrotor-9-dp-n30-s0" / "it2" / "eval", runs / "lone"
    for d, name in ((loop_eval, "quadrotor-9-dp-n30-s0"), (lone, "lone")):
        d.mkdir(parents=True)
        write_evaluation([{**row, "run": name, "iteration": 2}], d / "eval.csv", [{"rollouts": None}])
        man = json.loads(manifest_path(d / "eval.csv").read_text())    # as format 1 wrote it: no entry git_rev
        man.update(format_version=1, git_rev="abc123")
        del man["entries"][0]["git_rev"]
        manifest_path(d / "eval.csv").write_text(json.dumps(man))
    (runs / "quadrotor-9-dp-n30-s0" / "loop_config.json").write_text(json.dumps({"n_algo": 5}))
    before = (lone / "eval.csv").read_bytes()
    with pytest.raises(SdpError, match=r"2 evaluation\(s\) under .* older code .* `sdp migrate "):
        load_runs(runs)
    r = CliRunner().invoke(app, ["migrate", str(runs)])
    assert r.exit_code == 0 and "migrated 2 evaluation(s)" in r.output, r.output
    df = load_runs(runs).set_index("run")
    assert df.loc["quadrotor-9-dp-n30-s0", "n_algo"] == 5 and pd.isna(df.loc["lone", "n_algo"])
    assert (df.git_rev == "abc123").all() and (df.policy_cost_mean == 1.5).all()
    assert (lone / "eval.csv").read_bytes() == before                         # nothing to add: kept as is
    assert (loop_eval / "eval.csv.v1").is_file() and (loop_eval / "eval.manifest.json.v1").is_file()
    assert json.loads(manifest_path(lone / "eval.csv").read_text())["format_version"] == LAYOUT
    snapshot = {p: p.read_bytes() for p in runs.rglob("*") if p.is_file()}
    r = CliRunner().invoke(app, ["migrate", str(runs)])
    assert r.exit_code == 0 and "migrated 0 evaluation(s)" in r.output and "2 already current" in r.output
    assert {p: p.read_bytes() for p in runs.rglob("*") if p.is_file()} == snapshot
    for name in ("eval.csv", "eval.manifest.json"):                              # format 1 again, corrupt config
        (loop_eval / name).write_bytes((loop_eval / (name + ".v1")).read_bytes())
    (runs / "quadrotor-9-dp-n30-s0" / "loop_config.json").write_text("{")
    with pytest.raises(SdpError, match="corrupt loop config"):
        migrate_evaluation(manifest_path(loop_eval / "eval.csv"))
    r = CliRunner().invoke(app, ["migrate", str(tmp_path / "nowhere")])
    assert r.exit_code == 1


def test_trajectory_titles_say_where_a_solve_did_not_converge():
    """The trajectory figure draws TO alone's last iterate where it failed: the panel must say so, and a
    policy's line says when the refine from its rollout did not converge."""
    import numpy as np

    from sdp_cli.report.figures.traj import _refine_note

    f = {"inst_pol_converged": np.array([True, False])}
    assert _refine_note(f, 0) == "" and _refine_note(f, 1) == ", refine not converged"
    assert _refine_note({}, 1) == ""                       # an older refine without the record: nothing claimed


def test_trajectory_figure_draws_each_method_at_its_own_last_iteration():
    """A loop partway (DP at iteration 3, SDP at 2) draws both methods, each at its last iteration; the rows of
    earlier iterations are left out."""
    import pandas as pd

    from sdp_cli.report.figures.traj import _last_iterations

    d = pd.DataFrame({"method": ["sdp", "sdp", "sdp", "dp", "dp", "dp", "dp"], "iteration": [0, 1, 2, 0, 1, 2, 3]})
    got = _last_iterations(d)
    assert sorted(zip(got.method, got.iteration)) == [("dp", 3), ("sdp", 2)]


def test_readme_names_the_seeds_each_code_revision_made():
    """A sweep run over several sessions mixes revisions: the README says which seeds each one made."""
    import pandas as pd

    from sdp_cli.report.make import revision_lines

    rows = [{"task": "quadrotor-0", "method": "sdp", "train_seed": s, "iteration": 0, "git_rev": rev, "epochs": e}
            for s, rev in ((0, "aaa"), (1, "bbb"), (2, "bbb")) for e in (10000, 20000)]
    lines = revision_lines(pd.DataFrame(rows))
    assert "| task | method | seeds | iterations | revision |" in lines
    assert lines[-2:] == ["| quadrotor-0 | sdp | 0 | 0 | `aaa` |", "| quadrotor-0 | sdp | 1,2 | 0 | `bbb` |"]
    assert revision_lines(pd.DataFrame(columns=["task", "method", "train_seed", "iteration", "git_rev"])) == []


def test_fig2b_counts_the_to_alone_solves_once_however_many_runs_repeat_them():
    """Two seeds of a method evaluated on the same 3 instances: the TO-alone histogram has 3 counts, not 6."""
    import pandas as pd

    from sdp_cli.report.figures.paper import _to_alone_once

    rows = [{"method": m, "guess": g, "iterations": it, "run": f"{m}-s{s}"}
            for m in ("dp", "sdp") for s in (0, 1) for g in ("naive", "policy") for it in (10, 12, 40)]
    assert sorted(_to_alone_once(pd.DataFrame(rows))) == [10, 12, 40]
    old = pd.DataFrame(rows).drop(columns="run")          # a table from before it had the column: kept whole
    assert len(_to_alone_once(old)) == 6


def test_fig1_infinity_rows_sit_above_every_mean_on_log_and_linear_axes(tmp_path, monkeypatch):
    """A diverged mean is drawn as ∞ at the top of fig1's cost axis, two rows of them; on a log axis a
    band 30% above the highest mean is a tenth of a decade, so the rows covered the highest curve (UR5).
    An interval reaching below zero runs off a log axis' bottom: "≤0" says so there. A spread of 30x or more is
    drawn on a log axis (UR5: an n_traj 2 mean of 540 flattened 6.4-16, where claim 1 is read, on a linear one)."""
    import pandas as pd

    from sdp_cli.report.figures import paper as figures

    for spread in (1e4, 10.0):            # log axis, linear axis
        rows = []
        for seed in range(2):
            dp_n4 = 60.0 + 900 * seed if spread > 1e3 else 60.0     # two far-apart seeds: mean 510 ± 5700
            low = 1.0 if spread > 1e3 else 10.0          # linear: 60 over 10 (log from 30x)
            for n, (sdp, dp) in {2: (spread, 50.0), 4: (20.0 + seed, dp_n4), 8: (low + seed, 1e9)}.items():
                rows += [{"task": "t", "iteration": 0, "method": m, "epochs": 100, "n_traj": n, "success_rate": 0.5,
                          "policy_cost_mean": c, "to_alone_cost_mean": low / 2} for m, c in (("sdp", sdp), ("dp", dp))]
        figs = []
        monkeypatch.setattr(figures, "save_fig", lambda fig, path: figs.append(fig) or path)
        figures.fig1(pd.DataFrame(rows), "t", tmp_path)
        ax = figs[0].axes[0]
        assert ax.get_yscale() == ("log" if spread > 1e3 else "linear")
        if spread < 1e3:    # 540 beside 6.4 (UR5's n_traj 2 and TO alone) goes on a log axis
            figures.fig1(pd.DataFrame(rows).replace({10.0: 6.4, 50.0: 540.0}), "t", tmp_path)
            assert figs[-1].axes[0].get_yscale() == "log"
        figs[0].canvas.draw()
        renderer = figs[0].canvas.get_renderer()
        marks = [t for t in ax.texts if t.get_text() == "∞"]
        assert len(marks) == 1
        highest = ax.transData.transform((8, max(spread, 60.0)))[1]     # display y of the highest mean
        assert min(t.get_window_extent(renderer).y0 for t in marks) > highest + 5   # clear of its marker
        assert marks[0].xy[1] < ax.get_ylim()[1]
        zeros = [t.xy[0] for t in ax.texts if t.get_text() == "≤0"]
        assert zeros == ([pytest.approx(4, rel=0.1)] if spread > 1e3 else [])     # DP's n_traj 4
    # two neighbouring curves (SDP at 1e4 and 2e4 epochs on UR5) reaching below zero at one n_traj: their "≤0"
    # sat side by side 1.07x apart on the n_traj axis and ran into one another ("≤00")
    costs = {2: (1e4, 1e4), 4: (60.0, 960.0), 8: (1.0, 2.0)}      # n_traj 4: mean 510 ± 5700
    both = pd.DataFrame([{"task": "t", "iteration": 0, "method": "sdp", "epochs": ep, "n_traj": n, "success_rate": 0.5,
                          "policy_cost_mean": c[seed], "to_alone_cost_mean": 0.5}
                         for ep in (100, 200) for n, c in costs.items() for seed in range(2)])
    figures.fig1(both, "t", tmp_path)
    figs[-1].canvas.draw()
    ax = figs[-1].axes[0]
    boxes = [t.get_window_extent(figs[-1].canvas.get_renderer()) for t in ax.texts if t.get_text() == "≤0"]
    assert len(boxes) == 2 and not boxes[0].overlaps(boxes[1])


def test_timing_table_counts_single_shooting_and_the_measured_wall(tmp_path):
    """At 38d2c04 the timing table left out the single-shooting baseline (about 19 s a fig2 evaluation) and gave
    total_s as a sum of parts (105 s reported, 126 s measured)."""
    import pandas as pd

    from sdp_cli.data.artifacts import save_timing
    from sdp_cli.algorithm.evaluate import write_evaluation
    from sdp_cli.report.figures.timing import timing_table

    pol = tmp_path / "run" / "it0" / "policy"
    pol.mkdir(parents=True)
    (pol / "metrics.csv").write_text("step,loss\n1,1.0\n10,0.5\n")
    save_timing(pol, {"wall_time": 30.0})
    ev = tmp_path / "run" / "it0" / "eval"
    row = {"task": "pendulum", "method": "sdp", "train_seed": 0, "iteration": 0, "policy": str(pol), "n": 10,
           "refined_solve_time_mean": 0.5, "refined_solved_rate": 1.0, "to_alone_solve_time_mean": 0.5,
           "ss_refined_solve_time_mean": 1.0, "ss_to_alone_solve_time_mean": 1.0, "data": None, "run": "run",
           "t_a": 8, "rollout_time": 2.0}
    write_evaluation([row], ev / "eval.csv", wall_time=70.0)
    df = pd.DataFrame([{**row, "source": str(ev)}])
    t = timing_table(df, "pendulum").iloc[0]
    assert t.eval_solve_s == 10.0 and t.eval_ss_solve_s == 20.0 and t.eval_wall_s == 70.0
    assert t.total_s == 30.0 + 70.0 and not t.total_measured      # collection time unknown here
    save_timing(ev / "eval.csv", {})                                 # an evaluation made before the wall was kept
    t = timing_table(df, "pendulum").iloc[0]
    assert pd.isna(t.eval_wall_s) and t.total_s == 30.0 + 2.0 + 10.0 + 20.0


def test_a_new_figure_is_one_registry_entry(tmp_path, monkeypatch):
    """A figure registered in sdp_cli.report.figures.FIGURES is drawn for every task, listed in the README and
    cleaned up when it is no longer written (here: the committed small report, regenerated from itself)."""
    import shutil
    from pathlib import Path

    import pandas as pd

    from sdp_cli.report import figures
    from sdp_cli.report.make import make_report

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "small"
    shutil.copytree(root / "results" / "small", out)
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path)               # no params.yaml / pipelines here: report what is there

    def toy(rows, task, out, carried):
        d = rows[rows.task == task].groupby("method").policy_cost_mean.mean().reset_index()
        path = out / f"toy_{task}.csv"
        d.to_csv(path, index=False)
        return [path]

    extra = figures.FIGURES + (figures.Figure("toy", toy),)
    monkeypatch.setattr(figures, "FIGURES", extra)
    monkeypatch.setattr(figures, "REPORT_FILE", __import__("re").compile(
        r"^(all_runs\.csv|README\.md|(" + "|".join(f.name for f in extra if not f.folder) + r")_.+\.(csv|md|png))$"))
    make_report(tmp_path / "empty", out, experiment="small", keep_missing=True)
    toy_csv = pd.read_csv(out / "toy_pendulum.csv")
    assert set(toy_csv.method) == {"sdp", "dp"} and "`toy_pendulum.csv`" in (out / "README.md").read_text()
    monkeypatch.setattr(figures, "FIGURES", extra[:-1])
    make_report(tmp_path / "empty", out, experiment="small", keep_missing=True)
    assert not (out / "toy_pendulum.csv").exists()        # stale: the registry no longer has it
    assert (out / ".superseded" / "toy_pendulum.csv").is_file()    # moved aside, not deleted


def test_runs_of_two_to_families_are_drawn_apart_with_their_own_to_alone(tmp_path, monkeypatch):
    """A task evaluated with the multiple-shooting TO and with the DDP (`sdp loop --to ddp`): the methods are
    drawn per family (`sdp-to-ddp`), each family's TO alone is its own line and table row; a task with one
    family keeps the plain names (the committed reports are unchanged). Fig. 1 drew one TO-alone line averaging
    both families (33.8 between fatrop's 31.7 and box-FDDP's 44.3), and Fig. 2b called box-FDDP's iterations
    "multiple shooting"."""
    import pandas as pd

    from sdp_cli.report.figures import paper
    from sdp_cli.report.figures.paper import fig1, fig2a, fig2b, table2c
    from sdp_cli.report.figures.style import COLORS
    from sdp_cli.report.rows import method_label
    from sdp_cli.report.rows import Variant, family_of, method_variants, plain_method

    rows = []
    for to, alone in (("ms", 31.5), ("ddp", 45.2)):
        for m, cost in (("sdp", 40.0), ("dp", 60.0)):
            for seed in (0, 1):
                rows.append({"task": "double_pendulum", "method": m, "to": to, "run": f"{m}-{to}-s{seed}",
                             "iteration": 0, "t_a": 4, "train_seed": seed, "epochs": 10, "n_traj": 30,
                             "policy_cost_mean": cost + seed, "refined_cost_mean": alone - 5, "success_rate": 0.5,
                             "to_alone_cost_mean": alone, "refined_solve_time_mean": 0.1,
                             "rollout_time_per_instance": 0.01})
    rows.append({**rows[0], "task": "pendulum", "to": None, "run": "p"})     # older row: no family recorded
    d = method_variants(pd.DataFrame(rows))
    dp2 = d[d.task == "double_pendulum"]
    assert set(dp2.method) == {"sdp-to-ms", "sdp-to-ddp", "dp-to-ms", "dp-to-ddp"}
    assert set(d[d.task == "pendulum"].method) == {"sdp"}
    assert {m.to for m in dp2.method} == {"ms", "ddp"}
    assert family_of(Variant("sdp", to="ddp")) == "ddp" and family_of("sdp") == "ms"
    assert plain_method(Variant("dp", k=5, to="ddp")) == "dp"
    assert method_label(Variant("sdp", to="ddp")) == "SDP (TO box-FDDP)"
    assert COLORS.get(Variant("sdp", to="ddp")) != COLORS.get(Variant("sdp", to="ms"))
    fig2a(dp2, "double_pendulum", tmp_path)
    tab = pd.read_csv(tmp_path / "fig2a_double_pendulum.csv")
    alone = tab[tab.curve == "TO alone"].set_index("method")["mean"].to_dict()
    assert alone == {"to-ms": 31.5, "to-ddp": 45.2}
    table2c(dp2, "double_pendulum", tmp_path)
    t = pd.read_csv(tmp_path / "table2c_double_pendulum.csv").set_index("method")
    assert t.loc["sdp-to-ddp", "TO alone cost"] == 45.2 and t.loc["sdp-to-ms", "TO alone cost"] == 31.5
    figs = []
    monkeypatch.setattr(paper, "save_fig", lambda fig, path: figs.append(fig) or path)
    fig1(dp2, "double_pendulum", tmp_path)      # a TO-alone line per family, not one mixing both
    f1 = pd.read_csv(tmp_path / "fig1_double_pendulum.csv").set_index("method")
    assert f1.loc["dp-to-ddp", "to_alone_mean"] == 45.2 and f1.loc["dp-to-ms", "to_alone_mean"] == 31.5
    # one row of panels per family (16 curves in one panel were unreadable), on the same cost axis
    cost_axes = figs[0].axes[0::2]
    lines = [{ln.get_label(): ln.get_ydata()[0] for ln in a.lines if ln.get_label().startswith("TO")} for a in cost_axes]
    assert lines == [{"TO alone (fatrop)": 31.5}, {"TO alone (box-FDDP)": 45.2}]
    drawn = [{t.get_label().split(" (")[0] + " " + t.get_label().split("(")[1].split(")")[0]
              for t in a.containers} for a in cost_axes]
    assert drawn == [{"SDP TO fatrop", "DP TO fatrop"}, {"SDP TO box-FDDP", "DP TO box-FDDP"}]
    assert cost_axes[0].get_ylim() == cost_axes[1].get_ylim()

    class Carried:      # an earlier report's per-instance iterations (the runs' files gone)
        def rows(self, name, task, last):
            return pd.DataFrame([{"solver": s, "method": m, "guess": g, "iterations": 7, "run": m + "-s0"}
                                 for s in ("multiple shooting", "single shooting") for m in ("sdp-to-ms", "sdp-to-ddp")
                                 for g in ("policy", "naive")])
    fig2b(dp2.assign(refined=None), "double_pendulum", tmp_path, Carried())
    b = pd.read_csv(tmp_path / "fig2b_double_pendulum.csv")     # the loop's TO named by its family
    assert set(zip(b.solver, b.method)) == {("multiple shooting", "sdp-to-ms"), ("box-FDDP", "sdp-to-ddp"),
                                            ("single shooting", "sdp-to-ms"), ("single shooting", "sdp-to-ddp")}
    assert [a.get_xlabel() for a in figs[-1].axes] == ["TO iterations, multiple shooting", "TO iterations, box-FDDP",
                                                       "TO iterations, single shooting"]


def test_readme_names_the_results_version_of_each_runs_rows():
    """Loops record the results version (what runs measure) in their rows since version 4: the README's revision
    table gives it per task, method and revision; a row whose version is unknown (not recorded, and git does not
    know its revision) says so; reports whose rows have none keep the table without the column."""
    import pandas as pd

    from sdp_cli.report.make import revision_lines

    rows = pd.DataFrame({"task": ["pendulum"] * 3, "method": ["sdp", "sdp", "dp"], "train_seed": [0, 1, 0],
                         "iteration": [0, 0, 0], "git_rev": ["abc", "abc", "old"], "results_version": [4, 4, None]})
    lines = revision_lines(rows)
    assert "| task | method | seeds | iterations | revision | results version |" in lines
    assert "| pendulum | sdp | 0,1 | 0 | `abc` | 4 |" in lines
    assert "| pendulum | dp | 0 | 0 | `old` | unknown |" in lines
    old = revision_lines(rows.drop(columns="results_version"))
    assert "| task | method | seeds | iterations | revision |" in old and "| pendulum | dp | 0 | 0 | `old` |" in old


def test_a_report_interrupted_midway_leaves_the_earlier_one_as_it_was(tmp_path, monkeypatch):
    """Until 2026-11-27 `sdp report` wrote into its folder file by file: an error or Ctrl-C after fig1 left a
    folder mixing two reports (a new all_runs.csv and fig1 beside the old fig2a and README). Every byte of the
    earlier report must stay until the new one is complete, and no staging folder is left behind."""
    import shutil
    from pathlib import Path

    from sdp_cli.report import figures
    from sdp_cli.report.make import make_report

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "small"
    shutil.copytree(root / "results" / "small", out)
    for p in out.glob("fig1_*.csv"):       # an earlier report that the new one will differ from
        p.write_text(p.read_text() + "earlier\n")
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path)

    def broken(rows, task, out, carried):
        raise KeyboardInterrupt

    monkeypatch.setattr(figures, "FIGURES", figures.FIGURES[:3] + (figures.Figure("broken", broken),)
                        + figures.FIGURES[3:])
    with pytest.raises(KeyboardInterrupt):
        make_report(tmp_path / "empty", out, experiment="small", keep_missing=True)
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "small"]      # no staging folder left
    monkeypatch.setattr(figures, "FIGURES", figures.FIGURES[:3] + figures.FIGURES[4:])
    written = make_report(tmp_path / "empty", out, experiment="small", keep_missing=True)
    assert all(p.is_file() and out in p.parents for p in written)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "small"]


def test_results_version_of_rows_without_one_is_read_from_their_code_revision(tmp_path):
    """Runs before results version 4 did not record it: the report gives each such row the
    ``RESULTS_VERSION`` literal at its code revision (1 before the constant existed, the older of a
    ``rollouts+refinement`` pair, unknown where git cannot tell), and keeps a recorded one as it is."""
    import math
    import subprocess

    import pandas as pd

    from sdp_cli.report.versions import version_at, version_text, with_results_version

    repo = tmp_path / "repo"
    (repo / "sdp_cli").mkdir(parents=True)
    git = lambda *a: subprocess.run(["git", *a], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()  # noqa: E731
    git("init", "-q")
    revs = []
    for text in ('__version__ = "0.1.0"\n', "RESULTS_VERSION = 2\n", "RESULTS_VERSION = 3  \n",
                 "RESULTS_VERSION = max(HISTORY)\n"):
        (repo / "sdp_cli" / "__init__.py").write_text(text)
        git("add", "-A")
        git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
        revs.append(git("rev-parse", "HEAD"))
    assert [version_at(r, repo) for r in revs[:3]] == [1.0, 2.0, 3.0]
    assert math.isnan(version_at(revs[3], repo))                       # not an integer literal: unknown
    assert math.isnan(version_at("0" * 40, repo)) and math.isnan(version_at("unknown", repo))
    df = pd.DataFrame({"git_rev": [revs[0], f"{revs[1]}+dirty", f"{revs[2]}+{revs[1]}", "unknown", revs[0]],
                       "results_version": [None, None, None, None, 4]})
    got = with_results_version(df, repo).results_version.tolist()
    assert got[:3] == [1.0, 2.0, 2.0] and math.isnan(got[3]) and got[4] == 4.0
    assert with_results_version(df.drop(columns="results_version"), repo).results_version.tolist()[4] == 1.0
    assert version_text(got) == "1, 2, 4, unknown" and version_text([4.0, 4.0]) == "4"
    assert version_text([math.nan]) == "unknown"


def test_results_version_at_this_repository_head():
    """The literal the report parses at an old revision is the one the package runs with."""
    import subprocess
    from pathlib import Path

    import sdp_cli
    from sdp_cli.report.versions import version_at

    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(sdp_cli.__file__).parents[1],
                          capture_output=True, text=True, check=True).stdout.strip()
    assert version_at(head) == sdp_cli.RESULTS_VERSION
    assert max(sdp_cli.RESULTS_HISTORY) == sdp_cli.RESULTS_VERSION
    assert sorted(sdp_cli.RESULTS_HISTORY) == list(range(1, sdp_cli.RESULTS_VERSION + 1))


def test_an_older_row_stays_beside_a_newer_version_that_does_not_touch_it():
    """Versions 5 and 7 changed the diffusion policies only (the quadrotor's conversion, compiled training): the
    MLPs' quadrotor-0 rows of version 4 stay beside SDP's of version 7, while DP's of version 4 there do not (the
    conversion changed what they measure); a version without a scope (4) touches every row; box-FDDP's version 6
    touches `-ddp` rows and loops of several iterations."""
    import pandas as pd

    from sdp_cli.report.rows import newest_version

    rows = pd.DataFrame({
        "run": ["q-sdp", "q-dp", "q-pddp", "q-pddps", "p-sdp", "p-pddp-v1", "p-pddp-ddp", "p-sdp-ddp",
                "l-dp", "l-sdp", "l-pddp"],
        "task": ["quadrotor-0"] * 4 + ["pendulum"] * 4 + ["double_pendulum"] * 3,
        "method": ["sdp", "dp", "pddp", "pddp_s", "sdp", "pddp", "pddp", "sdp", "dp", "sdp", "pddp"],
        "to": [None] * 6 + ["ddp", "ddp"] + [None] * 3,
        "n_algo": [1] * 8 + [5, 5, 5],
        "results_version": [7, 4, 4, 4, 7, 1, 4, 6, 4, 6, 4]})
    kept = set(newest_version(rows).run)
    assert kept == {"q-sdp", "q-pddp", "q-pddps", "p-sdp", "p-sdp-ddp", "l-sdp"}, kept


def test_a_task_s_rows_of_an_older_results_version_are_not_drawn_beside_a_newer_one(tmp_path):
    """A re-run fills a report run by run while `--keep-missing` keeps the earlier rows: UR5(0, 0) was redefined
    between results versions 1 and 4 (TO alone 0.059 vs 6.28), so a curve or a ledger interval mixing them
    measures nothing. Per task and TO family only the newest version is read; another family's or task's older
    rows stay (fig2: fatrop's runs of version 1 beside box-FDDP's of version 4); rows of unknown version stay."""
    import pandas as pd

    from sdp_cli.report.ledger import load_results
    from sdp_cli.report.rows import newest_version

    rows = pd.DataFrame({
        "run": ["u-s0", "u-s1", "u-s2", "p-s0", "p-s0-ddp", "q-s0", "u-old"],
        "task": ["ur5-fixed"] * 3 + ["pendulum"] * 2 + ["quadrotor-0", "ur5-fixed"],
        "to": [None, None, None, None, "ddp", None, None],
        "results_version": [1, 4, 4, 1, 4, 1, None],
        "policy_cost_mean": [90.0, 7.0, 8.0, 20.0, 21.0, 1.0, 50.0]})
    kept = newest_version(rows)
    assert list(kept.run) == ["u-s1", "u-s2", "p-s0", "p-s0-ddp", "q-s0", "u-old"]
    assert newest_version(rows.drop(columns="results_version")).equals(rows.drop(columns="results_version"))
    (tmp_path / "fig1").mkdir()
    rows.to_csv(tmp_path / "fig1" / "all_runs.csv", index=False)
    res = load_results(tmp_path)
    assert sorted(res["fig1"].run) == ["p-s0", "q-s0", "u-old", "u-s1", "u-s2"] and list(res["fig1/ddp"].run) == ["p-s0-ddp"]


def test_a_ledger_row_names_the_conversion_its_chunked_rows_used():
    import numpy as np
    import pandas as pd

    from sdp_cli.report.rows import conversion_text

    rows = pd.DataFrame({"conversion": [np.nan, "tracking"], "k_rollout": [5, 5]})
    assert conversion_text(rows) == " (inverse dynamics, tracking)"     # before the column: inverse dynamics
    assert conversion_text(rows.iloc[1:]) == " (tracking)"
    assert conversion_text(pd.DataFrame({"conversion": [np.nan], "k_rollout": [5]})) == ""   # acts on controls
    assert conversion_text(pd.DataFrame({"k_rollout": [5]})) == ""

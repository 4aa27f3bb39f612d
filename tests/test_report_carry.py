"""`sdp report --keep-missing`: a report extended by new runs keeps the earlier report's runs whose run
folders are gone (another machine), and regenerates the same tables from them."""

from __future__ import annotations

import pandas as pd
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.errors import SdpError
from sdp_cli.algorithm.evaluate import write_evaluation
from sdp_cli.report.carry import Carried
from sdp_cli.report.rows import Variant, plain_method
from sdp_cli.report.make import make_report

ROW = {"task": "pendulum", "method": "sdp", "n_traj": 3, "t_a": 8, "k_rollout": 5, "train_seed": 0, "epochs": 700,
       "test_seed": 0, "n": 20, "policy_cost_median": 0.0, "success_rate": 0.5, "rollout_time": 1.0,
       "diverged": 0, "controls_violation_rate": 0.0, "terminal_cost_mean": 0.0}
NO_FILES = {"rollouts": None, "refined": None, "policy": None, "data": None}


def _evaluate(root, run, cost, method="sdp", seed=0):
    d = root / run / "it0" / "eval"
    d.mkdir(parents=True, exist_ok=True)
    write_evaluation([{**ROW, "method": method, "train_seed": seed, "run": run, "iteration": 0,
                       "policy_cost_mean": cost}], d / "eval.csv", [NO_FILES])


@pytest.fixture
def two_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)      # no params.yaml / pipelines here: every run under --runs is reported
    runs, out = tmp_path / "runs", tmp_path / "results" / "exp"
    for run, cost, method, seed in (("a-dp-s0", 30.0, "dp", 0), ("b-sdp-s0", 10.0, "sdp", 0), ("c-sdp-s1", 12.0, "sdp", 1)):
        _evaluate(runs, run, cost, method, seed)
    make_report(runs, out, "exp")
    return runs, out


def test_runs_whose_folders_are_gone_keep_their_rows(two_runs):
    import shutil

    runs, out = two_runs
    before = (out / "all_runs.csv").read_bytes()
    shutil.rmtree(runs / "a-dp-s0")
    logs = []
    make_report(runs, out, "exp", log=logs.append, keep_missing=True)
    assert (out / "all_runs.csv").read_bytes() == before          # same table, whichever runs are carried
    assert any("keeping 1 row(s) of 1 run(s)" in s for s in logs)
    readme = (out / "README.md").read_text()
    assert "--keep-missing" in readme and "| pendulum | dp | 1 |" in readme
    assert "fig1_pendulum.png" in readme                          # the figure still draws dp from the kept row
    assert "dp" in set(pd.read_csv(out / "fig1_pendulum.csv").method)
    # a run folder that is here replaces its earlier rows
    _evaluate(runs, "b-sdp-s0", 5.0)
    make_report(runs, out, "exp", keep_missing=True)
    rows = pd.read_csv(out / "all_runs.csv").set_index("run").policy_cost_mean
    assert rows.to_dict() == {"a-dp-s0": 30.0, "b-sdp-s0": 5.0, "c-sdp-s1": 12.0}
    # the earlier table's column order is kept (new runs add rows, not a reshuffle of older columns)
    table = pd.read_csv(out / "all_runs.csv")
    table[table.columns[::-1]].to_csv(out / "all_runs.csv", index=False)
    make_report(runs, out, "exp", keep_missing=True)
    assert list(pd.read_csv(out / "all_runs.csv").columns) == list(table.columns[::-1])
    # nothing under --runs at all: the report is regenerated from its own table
    shutil.rmtree(runs)
    runs.mkdir()
    make_report(runs, out, "exp", keep_missing=True)
    assert pd.read_csv(out / "all_runs.csv").set_index("run").policy_cost_mean.to_dict() == rows.to_dict()
    # without --keep-missing the report is of what is under --runs only
    _evaluate(runs, "c-sdp-s1", 12.0, seed=1)
    make_report(runs, out, "exp")
    assert list(pd.read_csv(out / "all_runs.csv").run) == ["c-sdp-s1"]


def test_readme_counts_kept_runs_of_an_older_results_version_too(two_runs):
    """A kept run of an older results version is in all_runs.csv but not drawn: the README's count of runs
    with no run folder names it, apart, instead of counting the drawn ones only."""
    import shutil

    from sdp_cli import RESULTS_VERSION

    runs, out = two_runs
    table = pd.read_csv(out / "all_runs.csv")
    table["results_version"] = [1 if r == "a-dp-s0" else RESULTS_VERSION for r in table.run]
    table.to_csv(out / "all_runs.csv", index=False)
    shutil.rmtree(runs)
    runs.mkdir()
    make_report(runs, out, "exp", keep_missing=True)
    assert set(pd.read_csv(out / "all_runs.csv").run) == {"a-dp-s0", "b-sdp-s0", "c-sdp-s1"}
    readme = (out / "README.md").read_text()
    assert ("3 run(s) have no run folder under --runs (1 of them of an older results version, kept in "
            "all_runs.csv but not drawn)") in readme
    kept = readme.split("## Runs kept from the earlier report")[1].split("##")[0]
    assert "| pendulum | sdp | 2 |" in kept and "| pendulum | dp |" not in kept    # the table: drawn runs


def test_per_run_files_of_kept_runs_stay(two_runs):
    """Training curves are per-run files the report writes from a run's folder: a kept run's stay, a
    file of a run the report no longer has goes."""
    import shutil

    runs, out = two_runs
    (out / "curves").mkdir()
    for run in ("a-dp-s0", "gone-s0"):
        (out / "curves" / f"{run}-it0.csv").write_text("step,loss\n1,0.5\n")
    shutil.rmtree(runs / "a-dp-s0")
    make_report(runs, out, "exp", keep_missing=True)
    assert sorted(p.name for p in (out / "curves").iterdir()) == ["a-dp-s0-it0.csv"]


def test_earlier_tables_give_the_rows_of_kept_runs(tmp_path):
    """By run where the table has the column; in tables from before it, the rows of a method with no
    run read from a folder (exactly the earlier report's rows of it), never of a method with one."""
    fresh = frozenset({("ur5", "sdp")})
    c = Carried(tmp_path, frozenset({"dp-n32", "sdp-n8"}), fresh)
    drawn = pd.DataFrame({"method": ["dp", "sdp"], "run": ["dp-n32", "sdp-n8"]})
    pd.DataFrame({"method": ["dp", "dp", "sdp", "pddp"], "iterations": [1, 2, 3, 4]}).to_csv(tmp_path / "old.csv", index=False)
    rows = c.rows("old.csv", "ur5", drawn)
    assert list(rows.iterations) == [1, 2] and list(rows.run) == ["dp-n32", "dp-n32"]    # given their run
    pd.DataFrame({"method": ["dp", "sdp", "sdp", "dp"], "run": ["dp-n32", "sdp-n8", "sdp-n32", None],
                  "iterations": [1, 2, 3, 4]}).to_csv(tmp_path / "new.csv", index=False)
    # sdp-n8 is carried but not drawn (another budget: fig2b's SDP at n_traj 16 stayed beside 32, "300 guesses")
    assert list(c.rows("new.csv", "ur5", drawn[drawn.method == "dp"]).iterations) == [1, 4]
    assert list(c.rows("new.csv", "ur5", drawn).iterations) == [1, 2, 4]
    # two carried runs of a method: which run a run-less row was is unknown, so it stays without one
    two = Carried(tmp_path, frozenset({"dp-n32-s0", "dp-n32-s1"}))
    rows = two.rows("old.csv", "ur5", pd.DataFrame({"method": "dp", "run": ["dp-n32-s0", "dp-n32-s1"]}))
    assert list(rows.iterations) == [1, 2] and rows.run.isna().all()
    assert c.rows("missing.csv", "ur5", drawn).empty
    drawn = pd.DataFrame({"method": ["sdp", "sdp", "dp"], "run": ["sdp-n8", "sdp-n32", "dp-n32"]})
    assert c.keeps_traj(drawn) and not c.keeps_traj(drawn[drawn.method == "sdp"])
    assert not Carried(tmp_path).keeps_traj(drawn)      # a plain report redraws


def test_trajectory_figure_is_kept_when_a_method_is_fresh_only_at_a_smaller_budget(tmp_path):
    """A second seed run at small n_traj only: the figure draws the largest budget, whose runs are all
    carried (their rollouts gone), so the earlier figure stays rather than one without that method."""
    c = Carried(tmp_path, frozenset({"sdp-n32-s0", "dp-n32-s0"}), frozenset({("q", "sdp"), ("q", "dp")}))
    drawn = pd.DataFrame({"task": "q", "method": ["sdp", "dp", "pddp"], "run": ["sdp-n32-s0", "dp-n32-s0", "pddp-n32-s1"]})
    assert c.keeps_traj(drawn)
    assert not c.keeps_traj(drawn[drawn.method == "pddp"])


def test_trajectory_figures_are_one_per_to_family_each_kept_on_its_own(tmp_path):
    """A task under fatrop and box-FDDP: one figure per family (one figure of both drew the first method's family's
    TO alone for every method, 16 series a panel), the main family's under the old name; a family whose runs are
    all carried keeps its earlier file while the other is redrawn; a task of one family keeps one plain figure."""
    from sdp_cli.report.figures.traj import traj, traj_parts, trajectories

    d = pd.DataFrame({"task": "p", "method": [Variant("sdp", to="ddp"), Variant("dp", to="ms"), Variant("sdp", to="ms"),
                                              Variant("dp", to="ddp")],
                      "run": ["s-ddp", "d", "s", "d-ddp"]})
    parts = traj_parts(d, "p")
    assert [(name, sorted(rows.method)) for name, rows in parts] == [
        ("traj_p.png", ["dp-to-ms", "sdp-to-ms"]), ("traj_p-to-ddp.png", ["dp-to-ddp", "sdp-to-ddp"])]
    assert [(n, len(r)) for n, r in traj_parts(d.assign(method=["sdp", "dp"] * 2), "p")] == [("traj_p.png", 4)]
    (tmp_path / "traj_p-to-ddp.png").write_bytes(b"earlier")
    c = Carried(tmp_path, frozenset({"s-ddp", "d-ddp"}))
    assert [c.kept_traj(rows, name) for name, rows in parts] == [False, True]
    rows = d.assign(rollouts=None, refined=None, iteration=0, t_a=4, success_rate=1.0, policy_cost_median=1.0)
    assert traj(rows, "p", tmp_path, c) == [tmp_path / "traj_p-to-ddp.png"]   # ms redrawn (no rollouts: none), ddp kept
    with pytest.raises(ValueError, match="several TO families"):
        trajectories(rows, "p", tmp_path)


def test_keep_missing_without_an_earlier_report_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").mkdir()
    with pytest.raises(SdpError, match="no earlier report"):
        make_report(tmp_path / "runs", tmp_path / "out", "exp", keep_missing=True)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "all_runs.csv").write_text("task,method\npendulum,sdp\n")
    r = CliRunner().invoke(app, ["report", "--runs", "runs", "--out", "out", "--keep-missing"])
    assert r.exit_code == 1 and "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert "no run/task columns" in r.output


def test_fig2b_keeps_run_less_rows_of_a_method_fresh_only_at_a_smaller_budget(tmp_path, monkeypatch):
    """fig2b draws each method's largest budget. DP's n_traj 32 run is carried (folder gone) and its fig2b
    rows predate the ``run`` column; new DP runs at n_traj 8 only must not drop them (they did: UR5 DP
    vanished from fig2b_ur5-fixed.png once DP had fresh runs at smaller budgets)."""
    import shutil

    monkeypatch.chdir(tmp_path)
    runs, out = tmp_path / "runs", tmp_path / "results" / "exp"

    def evaluate(run, n_traj, seed):
        d = runs / run / "it0" / "eval"
        d.mkdir(parents=True, exist_ok=True)
        write_evaluation([{**ROW, "method": "dp", "n_traj": n_traj, "train_seed": seed, "run": run, "iteration": 0,
                           "policy_cost_mean": 1.0}], d / "eval.csv", [NO_FILES])

    evaluate("dp-n32-s0", 32, 0)
    make_report(runs, out, "exp")
    earlier = pd.DataFrame({"solver": "multiple shooting", "method": "dp", "guess": ["policy", "policy", "naive"],
                            "iterations": [19, 21, 300]})
    earlier.to_csv(out / "fig2b_pendulum.csv", index=False)       # a table from before the run column
    shutil.rmtree(runs / "dp-n32-s0")
    evaluate("dp-n8-s1", 8, 1)
    make_report(runs, out, "exp", keep_missing=True)
    assert set(pd.read_csv(out / "all_runs.csv").run) == {"dp-n32-s0", "dp-n8-s1"}
    tab = pd.read_csv(out / "fig2b_pendulum.csv")
    assert sorted(tab[tab.guess == "policy"].iterations) == [19, 21]
    assert (out / "fig2b_pendulum.png").is_file()
    assert set(tab.run) == {"dp-n32-s0"}          # the carried run's rows now say whose they are ...
    evaluate("dp-n32-s1", 32, 1)                  # ... so a second seed at the drawn budget keeps them
    make_report(runs, out, "exp", keep_missing=True)
    tab = pd.read_csv(out / "fig2b_pendulum.csv")
    assert sorted(tab[tab.guess == "policy"].iterations) == [19, 21]


def test_a_carried_loop_keeps_its_rows_once_another_variant_of_its_method_is_drawn(tmp_path):
    """fig3: the (T_h 64, T_a 63) loop's fig2b rows were written as plain ``dp``/``sdp`` with no ``run``
    column while it was the task's only loop; once a (32, 16) loop runs, the methods are drawn as variants
    (``dp-h64-ta63``) and those rows must stay, named like their run (they were dropped: fig2b_ur5-rinit
    vanished). Rows carried by run are renamed too, so one table never names a run two ways."""
    c = Carried(tmp_path, frozenset({"dp-h64", "sdp-h64"}), frozenset({("ur5", "dp-h32-ta16"), ("ur5", "sdp-h32-ta16")}))
    drawn = pd.DataFrame({"method": [Variant("dp", pair=(64, 63)), Variant("sdp", pair=(64, 63)), Variant("dp", pair=(32, 16))],
                          "run": ["dp-h64", "sdp-h64", "dp-h32"]})
    pd.DataFrame({"method": ["dp", "dp", "sdp", "pddp"], "iterations": [1, 2, 3, 4]}).to_csv(tmp_path / "old.csv", index=False)
    rows = c.rows("old.csv", "ur5", drawn)
    assert list(rows.iterations) == [1, 2, 3]
    assert list(rows.method) == ["dp-h64-ta63", "dp-h64-ta63", "sdp-h64-ta63"]
    assert list(rows.run) == ["dp-h64", "dp-h64", "sdp-h64"]
    pd.DataFrame({"method": ["dp", "sdp"], "run": ["dp-h64", "sdp-h64"], "iterations": [1, 2]}).to_csv(tmp_path / "new.csv", index=False)
    assert list(c.rows("new.csv", "ur5", drawn).method) == ["dp-h64-ta63", "sdp-h64-ta63"]
    # two carried variants of one method: the plain name could be either, so its run-less rows stay out
    two = Carried(tmp_path, frozenset({"dp-h64", "dp-h32"}))
    both = pd.DataFrame({"method": [Variant("dp", pair=(64, 63)), Variant("dp", pair=(32, 16))], "run": ["dp-h64", "dp-h32"]})
    assert two.rows("old.csv", "ur5", both).empty
    # nor is a plain name borrowed while the plain method itself has a fresh run
    fresh_plain = Carried(tmp_path, frozenset({"dp-h64"}), frozenset({("ur5", "dp")}))
    assert fresh_plain.rows("old.csv", "ur5", drawn[drawn.run == "dp-h64"]).empty
    assert [plain_method(m) for m in (Variant("sdp", k=5, pair=(32, 16)), Variant("pddp+s", k=2),
                                      Variant("dp", pair=(64, 63)), "sdp")] == ["sdp", "pddp+s", "dp", "sdp"]


def test_readme_tables_name_the_variant_each_run_is_drawn_as(tmp_path, monkeypatch):
    """Runs of one method that the figures draw apart (here K 2 and K 5; Fig. 3's (T_h, T_a) loops alike) are
    apart in the README too: budgets, code revisions and kept runs per variant (they were one ``sdp`` row, and
    a revision row could not say which loop it meant)."""
    import shutil

    monkeypatch.chdir(tmp_path)
    runs, out = tmp_path / "runs", tmp_path / "results" / "exp"
    for run, k, cost in (("k2-sdp-s0", 2, 10.0), ("k5-sdp-s0", 5, 12.0)):
        d = runs / run / "it0" / "eval"
        d.mkdir(parents=True)
        write_evaluation([{**ROW, "k_rollout": k, "run": run, "iteration": 0, "policy_cost_mean": cost}],
                         d / "eval.csv", [NO_FILES])
    make_report(runs, out, "exp")
    readme = (out / "README.md").read_text()
    assert "| pendulum | sdp-K2 | 0 | 3 | 700 | 1 | 20 | 8 |" in readme
    assert "| pendulum | sdp-K5 | 0 | 3 | 700 | 1 | 20 | 8 |" in readme and "| pendulum | sdp | " not in readme
    revisions = [ln for ln in readme.splitlines() if ln.startswith("| ") and " | `" in ln]     # the revision table
    assert {"sdp-K2", "sdp-K5"} <= {ln.split(" | ")[1] for ln in revisions}
    shutil.rmtree(runs / "k2-sdp-s0")
    make_report(runs, out, "exp", keep_missing=True)
    readme = (out / "README.md").read_text()
    assert "| pendulum | sdp-K2 | 1 |" in readme and "| pendulum | sdp | " not in readme


def test_run_less_rows_of_a_table_with_runs_stay_without_one_when_their_method_has_several(tmp_path):
    """A table whose run column holds names and blanks (read as a string column): run-less rows of a method
    with several carried runs stay run-less (re-reporting fig2 over its box-FDDP runs once failed here)."""
    pd.DataFrame({"method": ["dp", "dp", "dp"], "run": ["dp-x-s0", None, None],
                  "iterations": [1, 2, 3]}).to_csv(tmp_path / "t.csv", index=False)
    c = Carried(tmp_path, frozenset({"dp-x-s0", "dp-x-s1"}))
    rows = c.rows("t.csv", "q", pd.DataFrame({"method": "dp", "run": ["dp-x-s0", "dp-x-s1"]}))
    assert list(rows.iterations) == [1, 2, 3] and list(rows.run[:1]) == ["dp-x-s0"] and rows.run[1:].isna().all()


def test_fig2b_names_each_methods_t_a_where_they_differ(tmp_path, monkeypatch):
    """The MLPs act one step at a time (T_a 1) and the diffusion policies T_a 31: the title said "T_a = 1,31"
    without whose is which. Each legend entry names its method's T_a; one T_a for all stays in the title."""
    from sdp_cli.report.figures import paper

    drawn = []
    monkeypatch.setattr(paper, "save_fig", lambda fig, path: drawn.append(fig) or path)
    rows = [{"task": "quadrotor-0", "method": m, "t_a": t_a, "iteration": 0, "run": f"{m}-s0", "refined": None}
            for m, t_a in (("sdp", 31), ("pddp", 1))]
    pd.DataFrame({"solver": "multiple shooting", "method": ["sdp", "sdp", "pddp", "sdp"],
                  "guess": ["policy", "policy", "policy", "naive"], "iterations": [19, 21, 40, 15],
                  "run": ["sdp-s0", "sdp-s0", "pddp-s0", "sdp-s0"]}).to_csv(tmp_path / "fig2b_quadrotor-0.csv", index=False)
    carried = Carried(tmp_path, frozenset({"sdp-s0", "pddp-s0"}))

    def texts():
        fig = drawn.pop()
        labels = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        title = fig.get_suptitle()
        paper.pyplot().close(fig)
        return title, labels

    paper.fig2b(pd.DataFrame(rows), "quadrotor-0", tmp_path, carried)
    title, labels = texts()
    assert "T_a =" not in title
    assert labels[0].startswith("TO alone (naive guess, "), labels   # the filled histogram's entry
    assert any("SDP: T_a 31, 2 guesses" in s for s in labels), labels
    assert any("PDDP: T_a 1, 1 guesses" in s for s in labels), labels
    paper.fig2b(pd.DataFrame(rows[:1]), "quadrotor-0", tmp_path, Carried(tmp_path, frozenset({"sdp-s0"})))
    title, labels = texts()
    assert "T_a = 31" in title and not any("T_a 31" in s for s in labels), (title, labels)
    # one method drawn at two T_a (e.g. a sweep's rows): the legend names both, the title none
    two = [dict(rows[0]), dict(rows[0], t_a=15, run="sdp-s1")]
    paper.fig2b(pd.DataFrame(two), "quadrotor-0", tmp_path, Carried(tmp_path, frozenset({"sdp-s0"})))
    title, labels = texts()
    assert "T_a =" not in title and any("T_a 15,31" in s for s in labels), (title, labels)
    # a method named with its TO family ("SDP (TO fatrop)"): one bracket, not "(TO fatrop) (T_a 31, ...)"
    fam = [dict(r, method=Variant(r["method"], to="ms")) for r in rows]
    pd.read_csv(tmp_path / "fig2b_quadrotor-0.csv").assign(method=lambda t: t.method + "-to-ms").to_csv(
        tmp_path / "fig2b_quadrotor-0.csv", index=False)
    paper.fig2b(pd.DataFrame(fam), "quadrotor-0", tmp_path, carried)
    title, labels = texts()
    assert any("SDP (TO fatrop): T_a 31, 2 guesses" in s for s in labels), labels
    assert not any(") (" in s for s in labels), labels


def test_fig2b_outlines_that_coincide_stay_visible(tmp_path, monkeypatch):
    """With fatrop every warm start took 8 iterations: DP's, PDDP's, PDDP+S's and SDP's step outlines coincided
    and the last one drawn hid the others (fig2b_double_pendulum's fatrop panel). Each is drawn narrower than the
    one before it, so every outline keeps a visible edge."""
    from matplotlib.patches import Polygon

    from sdp_cli.report.figures import paper

    drawn = []
    monkeypatch.setattr(paper, "save_fig", lambda fig, path: drawn.append(fig) or path)
    methods = ("dp", "pddp", "pddp_s", "sdp")
    rows = [{"task": "double_pendulum", "method": m, "t_a": 4, "iteration": 4, "run": f"{m}-s0", "refined": None}
            for m in methods]
    pd.DataFrame({"solver": "multiple shooting", "method": [*methods, "dp"], "guess": ["policy"] * 4 + ["naive"],
                  "iterations": [8, 8, 8, 8, 30], "run": [f"{m}-s0" for m in (*methods, "dp")]}
                 ).to_csv(tmp_path / "fig2b_double_pendulum.csv", index=False)
    paper.fig2b(pd.DataFrame(rows), "double_pendulum", tmp_path, Carried(tmp_path, frozenset(r["run"] for r in rows)))
    fig = drawn.pop()
    outlines = [p for p in fig.axes[0].patches if isinstance(p, Polygon) and not p.get_fill()]
    paper.pyplot().close(fig)
    widths = [p.get_linewidth() for p in outlines]
    assert len(widths) == 4, widths
    assert all(a - b >= 0.5 for a, b in zip(widths, widths[1:])), widths   # each visibly wider than the next

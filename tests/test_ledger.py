"""The claims ledger (results/PAPER.md): in sync with the committed reports, and its rules.

The first test regenerates the ledger from the committed ``results/*/all_runs.csv``,
``results/bench/*.csv`` and ``results/claims.yaml`` and compares it byte for byte with the committed
``results/PAPER.md``: a report re-made without re-writing the ledger (or a hand edit) fails it.
The others check the verdict rules on synthetic report rows.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.errors import SdpError
from sdp_cli.report.ledger import ledger_rows, read_claims, write_ledger
from sdp_cli.report.ledger.checks import experiments, judge_claim
from sdp_cli.report.ledger.verdicts import ratio_verdict

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"


def _bound_claims() -> dict:
    """Each claim of the committed results/claims.yaml, by id, as a function of the reports (and of the name of
    the loop's TO, the way the ledger judges a TO family)."""
    claims, shared = read_claims(RESULTS / "claims.yaml")
    return {c["id"]: (lambda c: lambda res, loop_to=None: judge_claim(
        c, res, shared, {"loop_to": loop_to} if loop_to else {}))(c) for c in claims}


C = _bound_claims()
fig2_only_sdp, speedup = C[5], C[13]
runner = CliRunner()


def _copy_reports(dst: Path) -> None:
    for p in (list(RESULTS.glob("*/all_runs.csv")) + list(RESULTS.glob("bench/*.csv"))
              + list(RESULTS.glob("estimates/*.txt")) + [RESULTS / "claims.yaml"]):
        (dst / p.relative_to(RESULTS)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(p, dst / p.relative_to(RESULTS))


def test_committed_ledger_is_regenerated_from_the_committed_reports(tmp_path):
    _copy_reports(tmp_path)
    out = write_ledger(tmp_path / "PAPER.md")
    assert out.read_text() == (RESULTS / "PAPER.md").read_text(), \
        "results/PAPER.md is stale: run `sdp report --ledger results/PAPER.md`"


def test_claim_notes_hold_no_dated_history():
    """results/claims.yaml says why ours differs; our numbers and their history live in the reports' NOTES.md
    (the yaml's header says so). Until 2026-12-06 its notes held dated history ("Since the last ledger
    (2026-11-28): ...") that went stale with every re-run."""
    import re

    claims, _ = read_claims(RESULTS / "claims.yaml")
    for c in claims:
        notes = str(c.get("notes") or "")
        assert not re.search(r"\b20\d\d-\d\d-\d\d\b", notes), f"claim {c['id']}: a date in its notes"
        assert "since the last ledger" not in notes.lower(), f"claim {c['id']}: history in its notes"


def test_rows_of_another_to_family_are_judged_apart(tmp_path):
    """A report holding runs of both TO families (fig2 with box-FDDP beside fatrop): the ledger's rules judge
    each family apart (``fig2``: fatrop's rows, ``fig2/ddp``: box-FDDP's) and a claim that needs fig2 gives both
    (``TO by fatrop: ...; TO by box-FDDP: ...``): fatrop's part is what it was without the other family's runs,
    however those score, and a verdict that differs is given per family."""
    import pandas as pd

    from sdp_cli.report.ledger import ledger_rows, load_results
    from sdp_cli.report.rows import newest_version

    _copy_reports(tmp_path)
    claims, rules = read_claims(tmp_path / "claims.yaml")
    path = tmp_path / "fig2" / "all_runs.csv"
    ms = pd.read_csv(path)
    ms = ms[ms["to"].astype(object).where(ms["to"].notna(), "ms") == "ms"] if "to" in ms else ms         # fatrop's runs alone first
    ms.to_csv(path, index=False)
    ref = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    ddp = ms.assign(to="ddp", run=ms.run + "-ddp", policy_cost_mean=1e9, success_rate=0.0)
    pd.concat([ms, ddp], ignore_index=True).to_csv(path, index=False)
    res = load_results(tmp_path)
    drawn = len(newest_version(ms))           # a task's rows of an older results version are not judged
    assert 0 < drawn and len(res["fig2"]) == drawn and len(res["fig2/ddp"]) == drawn
    assert (res["fig2/ddp"].to == "ddp").all() and not res["fig2"].run.str.endswith("-ddp").any()
    got = {r["id"]: r for r in ledger_rows(res, claims, rules)}
    for c in claims:
        a, b = ref[c["id"]], got[c["id"]]
        if "fig2" not in experiments(c):
            assert (a["ours"], a["verdict"]) == (b["ours"], b["verdict"]), c["id"]        # no fig2: as it was
            continue
        assert b["ours"].startswith(f"TO by fatrop: {a['ours'] or '—'}; TO by box-FDDP: "), c["id"]
        assert b["verdict"] == a["verdict"] or b["verdict"].startswith(f"{a['verdict']} (fatrop); "), c["id"]
    assert got[5]["verdict"] == f"{ref[5]['verdict']} (fatrop); not reproduced (box-FDDP)"   # no policy solves it
    assert "fig2 double_pendulum box-FDDP: " in got[13]["ours"].split("; TO by box-FDDP: ")[1]
    partway = ddp[ddp.iteration < ddp.iteration.max()]                     # a re-run filling up: no run finished
    pd.concat([ms, partway], ignore_index=True).to_csv(path, index=False)
    got = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    assert got[5]["ours"].endswith("; TO by box-FDDP: partway (no run finished yet)")
    assert got[5]["verdict"] == f"{ref[5]['verdict']} (fatrop); not run (box-FDDP)"
    assert "TO by box-FDDP: runs not finished (left out): " in got[5]["detail"]


def test_rows_name_the_results_version_of_their_runs(tmp_path):
    """Each row names the results version of the runs it reads, per TO family where they differ, and the header
    says what changed after the oldest (a verdict on runs made before the chunks covered the episode end must
    not read as one on the current code)."""
    from sdp_cli import RESULTS_HISTORY, RESULTS_VERSION
    from sdp_cli.report.ledger import load_results

    _copy_reports(tmp_path)
    claims, rules = read_claims(tmp_path / "claims.yaml")
    for p in tmp_path.glob("*/all_runs.csv"):
        pd.read_csv(p).assign(results_version=RESULTS_VERSION).to_csv(p, index=False)
    got = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    assert got[11]["runs"] == ""                                           # a bench: no runs
    assert {got[i]["runs"] for i in got if i != 11} == {str(RESULTS_VERSION)}
    text = write_ledger(tmp_path / "PAPER.md").read_text()
    assert f"Results version now: {RESULTS_VERSION}" in text and "What changed since" not in text
    path = tmp_path / "fig2" / "all_runs.csv"
    d = pd.read_csv(path)
    ms = (d["to"].astype(object).where(d["to"].notna(), "ms") == "ms") if "to" in d else pd.Series(True, d.index)
    if ms.all():                                                       # give fig2 a box-FDDP family of its own
        d = pd.concat([d, d.assign(to="ddp", run=d.run + "-ddp")], ignore_index=True)
        ms = pd.Series([True] * (len(d) // 2) + [False] * (len(d) // 2))
    d.loc[ms.values, "results_version"] = 1
    d.to_csv(path, index=False)
    got = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    assert got[5]["runs"] == f"1 (fatrop); {RESULTS_VERSION} (box-FDDP)"
    assert got[1]["runs"] == str(RESULTS_VERSION)                          # fig1 untouched
    text = write_ledger(tmp_path / "PAPER.md").read_text()
    assert f"| 1 (fatrop); {RESULTS_VERSION} (box-FDDP) | **" in text
    assert all(f"- version {v}: {RESULTS_HISTORY[v]}." in text for v in range(2, RESULTS_VERSION + 1))
    p = tmp_path / "fig4" / "all_runs.csv"                    # claim 10 reads quadrotor-9 only, claim 9 every layout
    d = pd.read_csv(p)
    d["results_version"] = (d["task"] == "quadrotor-9").map({True: 1, False: RESULTS_VERSION})
    d.to_csv(p, index=False)
    got = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    assert got[10]["runs"] == "1" and got[9]["runs"] == f"1, {RESULTS_VERSION}"
    p = tmp_path / "fig1" / "all_runs.csv"
    pd.read_csv(p).assign(results_version=None).to_csv(p, index=False)      # unknown (git did not know)
    got = {r["id"]: r for r in ledger_rows(load_results(tmp_path), claims, rules)}
    assert got[2]["runs"] == "unknown"


def test_every_claim_has_a_row_and_a_verdict():
    claims, _ = read_claims(RESULTS / "claims.yaml")
    assert [c["id"] for c in claims] == list(range(1, 14))
    text = (RESULTS / "PAPER.md").read_text()
    for c in claims:
        assert f"| {c['id']} | {c['claim']} |" in text
    rows = [ln for ln in text.splitlines() if ln.startswith("| ") and ln.split("|")[1].strip().isdigit()]
    assert len(rows) == 13
    verdicts = ("reproduced", "partly", "not reproduced", "not run")
    for r in rows:   # one verdict, or one per TO family: "partly (fatrop); not run (box-FDDP)"
        cell = r.rstrip(" |").rsplit("|", 1)[1].strip()
        assert cell.startswith("**") and cell.endswith("**"), r
        parts = cell.strip("*").split("; ")
        assert all(p in verdicts or p.rsplit(" (", 1)[0] in verdicts for p in parts), r


def test_ratio_rule():
    assert ratio_verdict(10.0, 18.6, 0.5, 0.1) == "reproduced"      # 9.0 >= 17.6 / 2
    assert ratio_verdict(9.0, 18.6, 0.5, 0.1) == "partly"
    assert ratio_verdict(2.8, 18.6, 0.5, 0.1) == "partly"           # 1.8 >= 1.76
    assert ratio_verdict(1.05, 18.6, 0.5, 0.1) == "not reproduced"
    assert ratio_verdict(0.5, 2.0, 0.5, 0.1) == "not reproduced"
    assert ratio_verdict(float("nan"), 2.0, 0.5, 0.1) == "not reproduced"


def test_ratio_kind_says_when_its_interval_straddles_a_verdict_line():
    from sdp_cli.report.ledger.kinds import Ratio

    r = Ratio(pd.Series([2.5, 3.0, 2.75]), paper=18.6, keep=0.5, partly=0.1, label="x")
    assert r.lines() == {"reproduced": pytest.approx(9.8), "partly": pytest.approx(2.76)}
    assert r.verdict == "not reproduced" and r.straddled() == ["partly"]     # 2.75 < 2.76 < 2.75 + 0.28
    assert r.text() == "x: 2.75x ± 0.283x (3 seeds; its interval straddles the verdict line: partly from 2.76x)"
    tight = Ratio(pd.Series([3.0, 3.0]), 18.6, 0.5, 0.1)
    assert tight.verdict == "partly" and tight.straddled() == [] and tight.text() == "3x ± 0x (2 seeds)"
    assert Ratio(pd.Series([3.0]), 18.6, 0.5, 0.1).straddled() == []        # one seed: no interval


def test_table2c_times_the_smallest_t_a_within_its_own_rows():
    """Claim 7: the speed-up at T_a 1 divides each T_a-1 row's own TO-alone time (never the mean over the sweep's
    rows, timed under other load), per seed; the degradation is the paper's: worst at T_a >= 12 over worst at
    T_a <= 9."""
    rows = []
    for seed in (0, 1):
        for t_a, cost, to in ((1, 30.0, 2.0), (4, 31.0, 8.0), (9, 33.5, 8.0), (12, 85.0, 8.0), (15, 137.0, 8.0)):
            rows.append(dict(task="double_pendulum", method="sdp", train_seed=seed, iteration=4, t_a=t_a,
                             run=f"dp-sdp-s{seed}", policy_cost_mean=cost, refined_solve_time_mean=0.1,
                             ss_refined_solve_time_mean=0.1, to_alone_solve_time_mean=to,
                             ss_to_alone_solve_time_mean=to, rollout_time_per_instance=1.0))
    r = C[7]({"fig2": pd.DataFrame(rows)})
    assert "single shooting: 20x ± 0x (2 seeds)" in r.ours          # pooled over the sweep it would read 68x
    assert "vs worst 33.5 at T_a <= 9 (4.09x)" in r.ours and r.verdict == "reproduced"
    assert "SDP at T_a 9 (the trade-off): rollout 1 s ± 0 s (2 seeds)" in r.ours     # shown, not judged
    d = pd.DataFrame(rows)
    d.loc[d.t_a == 1, "ss_to_alone_solve_time_mean"] = 0.2          # 2x at T_a 1: the speed-up is not reproduced
    assert C[7]({"fig2": d}).verdict == "partly"


def _fig2_rows(dp_success: float, sdp_done: int = 5) -> pd.DataFrame:
    """Synthetic fig2 report rows: SDP and DP, 2 seeds, 5 iterations; seed 1 of SDP stops at ``sdp_done``."""
    rows = []
    for method, succ, cost in (("sdp", 0.9, 31.0), ("dp", dp_success, 80.0)):
        for seed in (0, 1):
            n_it = sdp_done if (method == "sdp" and seed == 1) else 5
            for it in range(n_it):
                rows.append(dict(task="double_pendulum", method=method, train_seed=seed, iteration=it, t_a=4,
                                 run=f"double_pendulum-{method}-n30-s{seed}", policy_cost_mean=cost + 10 * max(0, 2 - it),
                                 success_rate=succ, refined_cost_mean=30.5, to_alone_solve_time_mean=0.3,
                                 refined_solve_time_mean=0.1, ss_to_alone_solve_time_mean=1.0,
                                 ss_refined_solve_time_mean=0.6))
    return pd.DataFrame(rows)


def test_only_sdp_solves_needs_every_method_and_failing_baselines():
    r = fig2_only_sdp({"fig2": _fig2_rows(dp_success=0.1)})
    assert r.verdict == "partly" and "; PDDP: not run yet; PDDP+S: not run yet" in r.ours   # named, as the paper
    r = fig2_only_sdp({"fig2": _fig2_rows(dp_success=0.7)})
    assert r.verdict == "partly" and "DP: success 70% ± 0% (2 seeds), cost 80 ± 0 (2 seeds)" in r.ours   # DP solves it too
    d = _fig2_rows(dp_success=0.1)
    assert fig2_only_sdp({"fig2": d.assign(success_rate=0.1)}).verdict == "not reproduced"   # SDP's is required
    assert fig2_only_sdp({"fig2": d[d.method == "dp"]}).verdict == "not run"
    d = _fig2_rows(dp_success=0.1)
    more = []
    for m in ("pddp", "pddp_s"):
        e = d[d.method == "dp"].copy()
        e["method"], e["run"] = m, e.run.str.replace("-dp-", f"-{m}-")
        more.append(e)
    assert fig2_only_sdp({"fig2": pd.concat([d, *more])}).verdict == "reproduced"
    assert "final distance" not in fig2_only_sdp({"fig2": d}).ours           # rows without the column


def test_final_distance_and_reaching_the_goal_beside_the_cost():
    """The ledger gives success and the final distance beside the paper's cost (claim 5), and whether TO's
    converged solutions reach the goal beside its convergence (claim 6: box-FDDP converges on every instance to
    optima that mostly miss it)."""
    d = _fig2_rows(dp_success=0.1)
    d["goal_distance_median"] = np.where(d.method == "sdp", np.where(d.train_seed == 0, 0.1, 0.3), 0.5)
    r = fig2_only_sdp({"fig2": d})
    assert "SDP: success 90% ± 0% (2 seeds), cost 31 ± 0 (2 seeds), final distance 0.2 m ± 0.196 m (2 seeds)" in r.ours
    assert "DP: success 10% ± 0% (2 seeds), cost 80 ± 0 (2 seeds), final distance 0.5 m ± 0 m (2 seeds)" in r.ours
    d = d.assign(to_alone_converged_rate=1.0, to_alone_iterations_mean=19.0, to_alone_cost_mean=44.0,
                 refined_iterations_mean=6.0, ss_to_alone_converged_rate=1.0, ss_to_alone_iterations_mean=100.0,
                 ss_refined_iterations_mean=20.0, ss_to_alone_cost_mean=34.0)
    r = C[6]({"fig2": d})
    assert r.ours.startswith("TO alone fails to converge (multiple shooting): 0% (TO iterations alone 19 ± 0 (2 seeds)")
    assert "reaches the goal" not in r.ours and r.verdict == "not reproduced"
    d = d.assign(to_alone_success_rate=0.08, refined_success_rate=np.where(d.train_seed == 0, 0.2, 0.4))
    r = C[6]({"fig2": d}, loop_to="box-FDDP")
    assert "TO alone fails to converge (box-FDDP): 0% (" in r.ours
    assert "TO alone reaches the goal 8% ± 0% (2 seeds), refined reaches the goal 30% ± 20% (2 seeds))" in r.ours
    r = C[6]({"fig2": d.assign(ss_to_alone_converged_rate=0.5)})        # single shooting fails half the time
    assert "TO alone fails to converge (single shooting): 50%" in r.ours and r.verdict == "partly"


def test_unfinished_runs_are_left_out_and_named():
    r = speedup({"fig2": _fig2_rows(dp_success=0.1, sdp_done=3)})
    assert "(1 seed)" in r.ours and "double_pendulum-sdp-n30-s1" in r.detail
    # multiple shooting 3x (reproduced), single shooting 1.67x (partly)
    assert r.verdict == "partly"


def test_claims_are_checks_of_a_few_kinds_and_bad_files_fail_cleanly(tmp_path):
    """The claims file alone says what judges a claim: its checks, each a kind with the report it reads and the
    paper's numbers; a claim none of whose reports exists is *not run* with the saved estimate's hours."""
    show = {"kind": "show", "experiment": "fig9", "columns": ["policy_cost_mean"]}
    claims = [{"id": 99, "claim": "c", "paper": "p", "checks": [show], "not_run": "est"}]
    assert ledger_rows({}, claims)[0]["verdict"] == "not run"
    assert ledger_rows({}, claims)[0]["detail"] == "est"
    # a claim not run gives the runs and hours of its experiment's saved estimate, never hand-written ones
    est = pd.DataFrame({"run": ["a", "b", "c"], "total_cpu_h": [1.25, 2.0, 0.5]})
    either = [{**claims[0], "checks": [show, {**show, "experiment": "fig8"}], "not_run": "not run yet."}]
    assert ledger_rows({"estimates/fig9": est}, either)[0]["detail"] == (
        "not run yet; fig9: 3 runs, 3.8 h in one process (`sdp pipeline fig9 --estimate`, results/estimates/fig9.txt)")
    base = {"kind": "reaches", "experiment": "fig1", "method": "sdp", "against": "dp",
            "tasks": ["pendulum", "ur5-fixed", "quadrotor-0"], "ratio": 5.0, "lower_bound_min": 3}
    two = [{"id": 2, "claim": "c", "paper": "p", "checks": [base]}]
    shared = {"solved": 0.5, "within": 0.1, "keep": 0.5, "partly": 0.1}
    with pytest.raises(SdpError, match="claim 2: the reports lack"):         # a report without the columns
        ledger_rows({"fig1": pd.DataFrame({"task": ["pendulum"]})}, two, shared)
    d = _fig1_rows()
    with pytest.raises(SdpError, match=r"claim 2, check 1 \(reaches\): results/claims.yaml gives no 'within'"):
        ledger_rows({"fig1": d}, two)                                        # a threshold missing
    # the paper's number is the yaml's: another ratio, another verdict, same code
    d = d.query("task == 'pendulum'")
    v = [ledger_rows({"fig1": d}, [{**two[0], "checks": [{**base, "ratio": r}]}], shared)[0]["verdict"]
         for r in (5.0, 200.0)]
    assert v[0] != v[1] and v[1] == "not reproduced"
    ok = {"id": 1, "claim": "c", "paper": "p"}
    for bad in ({"claims": [{"id": 1}]},
                {"claims": [{**ok, "checks": [{"kind": "nope", "experiment": "fig1"}]}]},      # unknown kind
                {"claims": [{**ok, "checks": "fig1"}]},                                        # not a list
                {"claims": [{**ok, "checks": [{**base, "nope": 1}]}]},                         # unknown field
                {"claims": [{**ok, "checks": [{"kind": "ratio", "experiment": "fig1", "method": "sdp"}]}]},   # no num
                {"claims": [{**ok, "checks": [{**base, "at": "sometime"}]}]},                  # a bad value
                {"claims": [{**ok, "checks": [{"kind": "ratio", "experiment": "fig1", "method": "sdp", "num": "a",
                                                "den": "b", "paper": 2, "baselines": ["nope"]}]}]}):
        (tmp_path / "claims.yaml").write_text(yaml.safe_dump({"rules": shared, **bad}))
        r = runner.invoke(app, ["report", "--ledger", str(tmp_path / "PAPER.md")])
        assert r.exit_code == 1 and "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "PAPER.md").exists()
    r = runner.invoke(app, ["report"])
    assert r.exit_code == 1 and "nothing to do" in r.output


def test_a_claim_of_a_new_shape_is_yaml_only():
    """A claim the paper might make that no claim of ours has made yet ("DP needs fewer TO iterations than TO
    alone on the double pendulum"): a yaml entry of existing kinds, judged, with its rule in words."""
    claim = {"id": 14, "claim": "c", "paper": "p", "checks": [
        {"kind": "solves", "experiment": "fig2", "method": "dp", "solves": False,
         "less": [["refined_iterations_mean", "to_alone_iterations_mean"]]},
        {"kind": "ratio", "experiment": "fig2", "method": "dp", "num": "to_alone_iterations_mean",
         "den": "refined_iterations_mean", "paper": 3, "label": "fewer iterations"}]}
    d = _fig2_rows(dp_success=0.1).assign(to_alone_iterations_mean=30.0, refined_iterations_mean=10.0)
    r = judge_claim(claim, {"fig2": d}, {"solved": 0.5, "keep": 0.5, "partly": 0.1})
    assert r.verdict == "reproduced" and "fewer iterations: 3x ± 0x (2 seeds)" in r.ours
    assert r.rule.startswith("DP does not solve (< 50% success), TO iterations from the policy < TO iterations alone")
    r = judge_claim(claim, {"fig2": d.assign(refined_iterations_mean=40.0)}, {"solved": 0.5, "keep": 0.5, "partly": 0.1})
    assert r.verdict == "not reproduced" and "TO iterations from the policy 40 vs TO iterations alone 30" in r.ours


def test_fig1_and_k_ablation_rules():
    k_steps, sdp_reaches_to = C[12], C[1]

    def fig1(never: str | None = None):
        rows = []
        for task in ("pendulum", "ur5-fixed", "quadrotor-0"):
            for n in (2, 4, 8):
                for seed in (0, 1):
                    cost = 100.0 if task == never else 10.0 * (1 + 8 / n) - 8   # 42, 22, 12 vs TO alone 11
                    rows.append(dict(task=task, method="sdp", n_traj=n, epochs=2000, train_seed=seed, iteration=0,
                                     policy_cost_mean=cost, to_alone_cost_mean=11.0))
        return pd.DataFrame(rows)

    r = sdp_reaches_to({"fig1": fig1()})
    assert r.verdict == "reproduced" and r.ours.count("from n_traj 8") == 3
    r = sdp_reaches_to({"fig1": fig1(never="ur5-fixed")})
    assert r.verdict == "partly" and ("ur5-fixed: TO alone 11, SDP within 10% never (over n_traj 2-8; lowest "
                                      "mean cost 100 at n_traj 2)") in r.ours
    # within 10% at n_traj 2 by chance, not at 4: "needs" counts from where it stays within
    d = fig1()
    d.loc[d.n_traj == 2, "policy_cost_mean"] = 11.5
    r = sdp_reaches_to({"fig1": d})
    assert r.ours.count("from n_traj 8 (first within at n_traj 2)") == 3 and r.verdict == "reproduced"
    r = sdp_reaches_to({"fig1": fig1().query("task != 'ur5-fixed'")})       # one of Fig. 1's tasks missing
    assert r.verdict == "partly" and "fig1 not run on ur5-fixed (SDP)" in r.detail

    def ablation(c5: float):
        return pd.DataFrame([dict(k_rollout=k, epochs=2000, train_seed=s, policy_cost_mean=c, success_rate=0.9,
                                  to_alone_cost_mean=14.0)
                             for k, c in ((2, 30.0), (5, c5), (10, 15.0)) for s in (0, 1, 2)])

    assert k_steps({"ablation_k": ablation(16.0)}).verdict == "reproduced"
    r = k_steps({"ablation_k": ablation(17.0)})                            # 13% above K = 10
    assert r.verdict == "not reproduced" and "K=5's mean cost 17 ± 0 (3 seeds) vs K=10's 15 ± 0 (3 seeds) (not within 10%)" in r.ours
    assert "SDP at K 2: cost 30 ± 0 (3 seeds), success 90% ± 0% (3 seeds)" in r.ours


def test_quadrotor_rules_per_layout():
    quadrotor9_times, quadrotor_precision = C[10], C[9]

    def fig4(dp_violates: float, layouts=("quadrotor-0", "quadrotor-1", "quadrotor-3", "quadrotor-9")):
        rows = []
        for task in layouts:
            n_it = 5 if task == "quadrotor-9" else 1
            for m, succ, viol, t_ref in (("sdp", 0.9, 0.0, 7.0), ("dp", 0.2, dp_violates, 9.0)):
                for seed in (0, 1):
                    for it in range(n_it):
                        rows.append(dict(task=task, method=m, train_seed=seed, iteration=it, t_a=16,
                                         run=f"{task}-{m}-s{seed}", success_rate=succ, violation_rate=viol,
                                         goal_distance_median=0.01 if m == "sdp" else 0.4,
                                         to_alone_solve_time_mean=16.0, refined_solve_time_mean=t_ref))
        return pd.DataFrame(rows)

    r = quadrotor_precision({"fig4": fig4(dp_violates=0.3)})
    assert r.verdict == "reproduced" and ("quadrotor-1, SDP: success 90% ± 0% (2 seeds), constraint violated 0% ± 0% "
                                          "(2 seeds), final distance 0.01 m ± 0 m (2 seeds); DP: success 20% ± 0% "
                                          "(2 seeds), constraint violated 30% ± 0% (2 seeds)") in r.ours
    assert quadrotor_precision({"fig4": fig4(dp_violates=0.0)}).verdict == "reproduced"     # no more often
    d = fig4(dp_violates=0.0)
    d.loc[(d.method == "sdp") & (d.task != "quadrotor-0"), "violation_rate"] = 0.5          # more often: not here
    assert quadrotor_precision({"fig4": d}).verdict == "partly"
    d.loc[d.task == "quadrotor-0", "violation_rate"] = np.where(d[d.task == "quadrotor-0"].method == "sdp", 0.5, 0.0)
    assert quadrotor_precision({"fig4": d}).verdict == "partly"           # quadrotor-0 (no obstacle) is exempt
    d = fig4(dp_violates=0.3)
    d["obstacles_violation_rate"] = np.where(d.method == "dp", 0.25, 0.0)
    d.loc[d.task == "quadrotor-0", "obstacles_violation_rate"] = np.nan                # no obstacle there
    r = quadrotor_precision({"fig4": d})
    assert "constraint violated 30% ± 0% (2 seeds), an obstacle hit 25% ± 0% (2 seeds)" in r.ours
    assert r.ours.startswith("quadrotor-0, SDP: success 90% ± 0% (2 seeds), constraint violated 0% ± 0% (2 seeds), final")
    assert quadrotor_precision({"fig4": fig4(dp_violates=0.3, layouts=("quadrotor-0",))}).verdict == "partly"
    d = fig4(dp_violates=0.3)
    d = d[~((d.task == "quadrotor-3") & (d.method == "sdp"))]                        # SDP not run there yet
    r = quadrotor_precision({"fig4": d})
    assert "quadrotor-3, SDP not run yet; DP: success 20% ± 0% (2 seeds)" in r.ours and r.verdict == "partly"
    r = quadrotor9_times({"fig4": fig4(dp_violates=0.3)})
    assert ("TO alone / from SDP in its own evaluation, multiple shooting: 2.29x ± 0x (2 seeds) (TO alone 16 s ± 0 s "
            "(2 seeds), refine 7 s ± 0 s (2 seeds)); DP on quadrotor-9 in its own evaluation: TO alone 16 s ± 0 s "
            "(2 seeds), refine 9 s ± 0 s (2 seeds)") == r.ours and r.verdict == "reproduced"   # 2.29x vs 2.09x
    # the ratio is the SDP loop's own evaluation's: a slower TO alone timed in DP's evaluation does not count
    d = fig4(dp_violates=0.3)
    d.loc[d.method == "dp", "to_alone_solve_time_mean"] = 40.0
    d.loc[d.method == "sdp", "to_alone_solve_time_mean"] = 9.0
    r = quadrotor9_times({"fig4": d})
    assert "multiple shooting: 1.29x ± 0x (2 seeds)" in r.ours and r.verdict == "partly"   # pooled: 3.5x
    assert quadrotor9_times({"fig4": fig4(0.3, layouts=("quadrotor-0",))}).verdict == "not run"
    # a loop partway (3 of its n_algo 5 iterations) is no final iteration, even when no run of the task is further
    d = fig4(dp_violates=0.3).assign(n_algo=lambda x: np.where(x.task == "quadrotor-9", 5, 1))
    part = d[(d.task != "quadrotor-9") | ((d.method == "dp") & (d.iteration < 3))]
    r = quadrotor9_times({"fig4": part})
    assert r.verdict == "not run" and r.detail == "runs not finished (left out): quadrotor-9-dp-s0, quadrotor-9-dp-s1"
    assert r.ours == "TO alone / from SDP in its own evaluation, SDP on quadrotor-9: not run yet"
    r = quadrotor_precision({"fig4": part})
    assert "quadrotor-9" not in r.ours and "quadrotor-9-dp-s0" in r.detail
    # DP finished, SDP partway (at 2 of 5): DP's final times shown, never judged; claim 9 names SDP unfinished
    part = d[(d.task != "quadrotor-9") | (d.method == "dp") | (d.iteration < 2)]
    r = quadrotor9_times({"fig4": part})
    assert r.verdict == "not run" and r.ours.startswith(
        "TO alone / from SDP in its own evaluation, SDP on quadrotor-9: partway (no run at its final iteration yet); "
        "DP on quadrotor-9 in its own evaluation: TO alone 16 s") and "quadrotor-9-sdp-s0" in r.detail
    assert "quadrotor-9, SDP not finished; DP: success 20% ± 0% (2 seeds)" in quadrotor_precision({"fig4": part}).ours


def _fig1_rows():
    """Synthetic fig1: SDP within 10% of TO alone from n_traj 4, DP from 32 (8x); PDDP and PDDP+S diverge in half
    of their evaluations, PDDP+S solves UR5(0, 0) at n_traj 8 and 16 only."""
    rows = []
    for task in ("pendulum", "ur5-fixed", "quadrotor-0"):
        for n in (1, 2, 3, 4, 8, 16, 32, 64):
            for seed in (0, 1):
                for m, cost, succ, div in (("sdp", 10.0 if n >= 4 else 20.0, 0.9 if n >= 3 else 0.1, 0),
                                          ("dp", 10.0 if n >= 32 else 30.0, 0.1, 0),
                                          ("pddp", 60.0, 0.0, seed),
                                          ("pddp_s", 50.0, 0.9 if 8 <= n <= 16 else 0.0, seed)):
                    rows.append(dict(task=task, method=m, n_traj=n, epochs=2000, train_seed=seed, iteration=0,
                                     policy_cost_mean=cost, success_rate=succ, diverged=div, to_alone_cost_mean=10.0))
    return pd.DataFrame(rows)


def test_fig1_claims_on_synthetic_rows():
    dp_needs_more, mlp_unstable, pendulum_torque = C[2], C[4], C[3]

    r = dp_needs_more({"fig1": _fig1_rows()})
    assert r.verdict == "reproduced" and "pendulum: SDP from n_traj 4, DP from n_traj 32 (8x)" in r.ours
    d = _fig1_rows()
    d.loc[(d.method == "dp"), "policy_cost_mean"] = 30.0                 # DP never: a lower bound 64 / 4
    assert "DP never (over n_traj 1-64; lowest mean cost 30 at n_traj 1) (> 16x)" in dp_needs_more({"fig1": d}).ours
    # DP run up to n_traj 16 while the MLPs ran up to 64: the bound is DP's largest dataset, 16 / 4
    short = d[(d.method != "dp") | (d.n_traj <= 16)]
    assert "DP never (over n_traj 1-16; lowest mean cost 30 at n_traj 1) (> 4x)" in dp_needs_more({"fig1": short}).ours
    part = dp_needs_more({"fig1": _fig1_rows().query("task == 'pendulum'")})   # one of Fig. 1's three tasks
    assert part.verdict == "partly" and "fig1 not run on ur5-fixed (SDP, DP), quadrotor-0 (SDP, DP)" in part.detail
    # a task with PDDP+S runs only is still missing for a claim about SDP and DP
    d = _fig1_rows()
    d = d[(d.task == "pendulum") | (d.method == "pddp_s")]
    part = dp_needs_more({"fig1": d})
    assert part.verdict == "partly" and "fig1 not run on ur5-fixed (SDP, DP), quadrotor-0 (SDP, DP)" in part.detail
    # DP without SDP on a task names SDP only
    d = _fig1_rows()
    d = d[(d.task == "pendulum") | (d.method == "dp")]
    assert "fig1 not run on ur5-fixed (SDP), quadrotor-0 (SDP)" in dp_needs_more({"fig1": d}).detail
    d = _fig1_rows()
    d.loc[d.method == "dp", "policy_cost_mean"] = 10.0                   # DP as good as SDP: 1x everywhere
    assert dp_needs_more({"fig1": d.query("task == 'pendulum'")}).verdict == "not reproduced"
    d = _fig1_rows()
    d.loc[(d.method == "dp") & (d.n_traj == 1), "policy_cost_mean"] = 10.5   # DP within at n_traj 1 only
    r = dp_needs_more({"fig1": d})
    assert "SDP from n_traj 4, DP from n_traj 32 (first within at n_traj 1) (8x)" in r.ours and r.verdict == "reproduced"
    d.loc[(d.method == "dp") & (d.n_traj > 1), "policy_cost_mean"] = 30.0  # ... and never again: "never" says so inside
    r = dp_needs_more({"fig1": d})
    assert ("DP never (over n_traj 1-64; lowest mean cost 10.5 at n_traj 1; first within at n_traj 1, left again at "
            "a larger one) (> 16x)") in r.ours
    assert mlp_unstable({"fig1": d[~d.method.isin(["pddp", "pddp_s"])]}).verdict == "not run"
    r = pendulum_torque({"fig1": _fig1_rows()})
    assert r.verdict == "reproduced" and r.ours.startswith("SDP on pendulum at n_traj 3: success 90% ± 0% (2 seeds)")
    assert "DP on pendulum: best success over n_traj 10% (n_traj 1)" in r.ours
    d = _fig1_rows()
    d.loc[(d.method == "dp") & (d.n_traj == 64), "success_rate"] = 0.6       # DP solves at one n_traj: partly
    assert pendulum_torque({"fig1": d}).verdict == "partly"
    r = mlp_unstable({"fig1": _fig1_rows()})
    assert r.verdict == "reproduced" and "PDDP+S on ur5-fixed at epochs 2000 solves at n_traj 8, 16" in r.ours
    assert ("evaluations with a diverged rollout, pendulum: DP 0%, PDDP 50%, PDDP+S 50%, SDP 0%; evaluations with a "
            "diverged rollout, quadrotor-0: DP 0%, PDDP 50%, PDDP+S 50%") in r.ours
    # a task where one MLP has run (a sweep under way) is named, not judged on that MLP alone, and the
    # verdict waits for it
    d = _fig1_rows()
    d = d[~((d.task == "quadrotor-0") & (d.method == "pddp_s"))]
    r = mlp_unstable({"fig1": d})
    assert r.verdict == "partly" and "quadrotor-0: DP 0%, PDDP 50%, SDP 0% (not judged: PDDP+S not run)" in r.ours
    # stable on the pendulum (many seeds), diverging on every UR5 evaluation (one seed): unstable per task,
    # whatever the pooled share says -> partly
    d = _fig1_rows()
    d.loc[d.task == "pendulum", "diverged"] = 0
    d.loc[(d.task == "ur5-fixed") & d.method.isin(["pddp", "pddp_s"]), "diverged"] = 30
    d = pd.concat([d[d.task != "ur5-fixed"]] * 5 + [d[(d.task == "ur5-fixed") & (d.train_seed == 0)]])
    d = d[d.task != "quadrotor-0"]
    r = mlp_unstable({"fig1": d})
    assert "ur5-fixed: DP 0%, PDDP 100%, PDDP+S 100%, SDP 0%" in r.ours and "pendulum: DP 0%, PDDP 0%, PDDP+S 0%, SDP 0%" in r.ours
    assert r.verdict == "partly"


def test_fig3_claim_per_horizon_and_action_length():
    ur5_long_actions = C[8]
    loops = ((32, 16), (32, 31), (64, 16), (64, 31), (64, 63))      # Fig. 3's, on both UR5 variants

    def fig3(pairs=loops, tasks=("ur5-rinit", "ur5-rinit-rtgt"), method="sdp", **cols):
        rows = []
        for task in tasks:
            for h, t_a in pairs:
                for it in range(5):
                    rows.append({**dict(task=task, method=method, horizon=h, t_a=t_a, train_seed=0, iteration=it,
                                        run=f"{task}-{method}-h{h}-ta{t_a}", success_rate=0.8, refined_iterations_mean=20,
                                        to_alone_iterations_mean=60, refined_cost_mean=5.0, to_alone_cost_mean=6.0,
                                        policy_cost_mean=7.0), **cols})
        return pd.DataFrame(rows)

    r = ur5_long_actions({"fig3": fig3()})
    assert r.verdict == "reproduced" and "ur5-rinit (T_h 64, T_a 63), SDP: success 80% (1 seed), cost 7 (1 seed), " \
        "TO iterations from the policy 20 vs TO iterations alone 60, cost refined from the policy 5 vs TO alone's cost 6" in r.ours
    assert ur5_long_actions({"fig3": fig3(refined_cost_mean=6.5)}).verdict == "not reproduced"   # costlier than TO alone
    assert ur5_long_actions({"fig3": fig3(pairs=loops[:3])}).verdict == "partly"               # Fig. 3's loops missing
    # DP alone says nothing of the claim: "not run", with DP's numbers and SDP named as missing
    dp = fig3(method="dp").assign(success_rate=0.1)
    r = ur5_long_actions({"fig3": dp})
    assert r.verdict == "not run" and "ur5-rinit (T_h 64, T_a 63), SDP not run yet; DP: success 10% (1 seed)" in r.ours
    started = pd.concat([dp, fig3().query("iteration < 2")])                # SDP partway: named as unfinished
    r = ur5_long_actions({"fig3": started})
    assert r.verdict == "not run" and r.detail.startswith("runs not finished (left out): ")
    assert "ur5-rinit-sdp-h64-ta63" in r.detail and "SDP not finished; DP" in r.ours and "not run yet" not in r.ours
    # SDP has finished one loop only: judged on it, DP beside it, the loops without any row named
    d = pd.concat([fig3(pairs=[(32, 16), (64, 63)], tasks=("ur5-rinit",), method="dp").assign(success_rate=0.1),
                   fig3(pairs=[(32, 16)], tasks=("ur5-rinit",))])
    r = ur5_long_actions({"fig3": d})
    assert "ur5-rinit (T_h 32, T_a 16), SDP: success 80% (1 seed)" in r.ours and "; DP: success 10% (1 seed)" in r.ours
    assert "ur5-rinit (T_h 64, T_a 63), SDP not run yet; DP: success 10%" in r.ours and r.verdict == "partly"
    assert r.detail == ("fig3 not run on ur5-rinit (T_h 32, T_a 31) (SDP, DP), ur5-rinit (T_h 64, T_a 16) (SDP, DP), "
                        "ur5-rinit (T_h 64, T_a 31) (SDP, DP), ur5-rinit-rtgt (T_h 32, T_a 16) (SDP, DP), "
                        "ur5-rinit-rtgt (T_h 32, T_a 31) (SDP, DP), ur5-rinit-rtgt (T_h 64, T_a 16) (SDP, DP), "
                        "ur5-rinit-rtgt (T_h 64, T_a 31) (SDP, DP), ur5-rinit-rtgt (T_h 64, T_a 63) (SDP, DP)")
    # with the saved estimate: each loop without rows carries the hours of its runs (SDP and DP of ur5-rinit
    # (32, 31): 3.0 h; none for a loop not estimated)
    est = pd.DataFrame({"run": ["ur5-rinit-sdp-n50-s0-h32-ta31", "ur5-rinit-dp-n50-s0-h32-ta31",
                                "ur5-rinit-rtgt-sdp-n100-s0-h32-ta31"],
                        "task": ["ur5-rinit"] * 2 + ["ur5-rinit-rtgt"], "total_cpu_h": [2.0, 1.0, 4.0]})
    r = ur5_long_actions({"fig3": d, "estimates/fig3": est})
    assert r.detail.startswith("fig3 not run on ur5-rinit (T_h 32, T_a 31) (SDP, DP) 3.0 h, ur5-rinit (T_h 64, T_a 16) "
                               "(SDP, DP), ")
    assert "ur5-rinit-rtgt (T_h 32, T_a 31) (SDP, DP) 4.0 h" in r.detail and r.detail.endswith(
        " (hours: the runs not made, `sdp pipeline fig3 --estimate` in one process, results/estimates/fig3.txt)")
    # SDP partway on (64, 63): "not finished" there
    d = pd.concat([d, fig3(pairs=[(64, 63)], tasks=("ur5-rinit",)).query("iteration < 2")])
    r = ur5_long_actions({"fig3": d})
    assert "ur5-rinit (T_h 64, T_a 63), SDP not finished; DP: success 10%" in r.ours
    assert "ur5-rinit-sdp-h64-ta63" in r.detail
    d = fig3()
    d = d[~((d.t_a == 63) & (d.iteration == 4))]                          # an unfinished run
    r = ur5_long_actions({"fig3": d})
    assert r.verdict == "partly" and "ur5-rinit-sdp-h64-ta63" in r.detail
    # claim 13: one speed-up per loop, not pooled over Fig. 3's (T_h, T_a) loops of a task
    d = fig3(pairs=[(32, 16), (64, 63)]).assign(to_alone_solve_time_mean=1.0)
    d["refined_solve_time_mean"] = np.where(d.t_a == 16, 0.1, 2.0)         # 10x from one loop, 0.5x from the others
    r = speedup({"fig3": d})
    assert "fig3 ur5-rinit (T_h 32, T_a 16) multiple shooting: 10x" in r.ours
    assert "fig3 ur5-rinit (T_h 64, T_a 63) multiple shooting: 0.5x" in r.ours and r.verdict == "partly"
    # rows evaluated before T_h was recorded belong to their task's one loop
    d = _fig2_rows(dp_success=0.1).assign(horizon=lambda x: np.where(x.train_seed == 0, 16.0, np.nan))
    assert "fig2 double_pendulum multiple shooting: 3x ± 0x (2 seeds)" in speedup({"fig2": d}).ours


def test_report_then_ledger_from_run_folders(tmp_path, monkeypatch):
    """`sdp report --runs ... --ledger ...`: the ledger's numbers come from the run folders through the
    report's all_runs.csv (here the K ablation, claim 12, from synthetic evaluations)."""
    from sdp_cli.algorithm.evaluate import write_evaluation

    monkeypatch.chdir(tmp_path)
    for k, cost in ((2, 30.0), (5, 15.5), (10, 15.0)):
        for seed in (0, 1):
            run = f"pendulum-sdp-n10-s{seed}-k{k}"
            d = tmp_path / "runs" / "ablation_k" / run / "it0" / "eval"
            d.mkdir(parents=True)
            row = {"task": "pendulum", "method": "sdp", "n_traj": 10, "t_a": 31, "k_rollout": k, "train_seed": seed,
                   "epochs": 2000, "test_seed": 0, "n": 50, "policy_cost_mean": cost + seed, "policy_cost_median": cost,
                   "success_rate": 0.8,
                   "diverged": 0, "to_alone_cost_mean": 14.0, "rollout_time": 1.0, "run": run, "iteration": 0}
            write_evaluation([row], d / "eval.csv", [{"rollouts": None, "refined": None, "policy": None, "data": None}])
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "claims.yaml").write_text(yaml.safe_dump({
        "rules": {"solved": 0.5, "within": 0.1, "keep": 0.5, "partly": 0.1}, "claims": [
            {"id": 12, "claim": "K = 5 diffusion steps suffice", "paper": "K = 5", "checks": [
                {"kind": "show", "experiment": "ablation_k", "at": "final_epochs", "method": "sdp", "per": ["k_rollout"],
                 "columns": ["policy_cost_mean"]},
                {"kind": "within", "experiment": "ablation_k", "at": "final_epochs", "method": "sdp",
                 "value": {"where": {"k_rollout": 5}, "column": "policy_cost_mean", "label": "K=5"},
                 "reference": {"where": {"k_rollout": 10}, "column": "policy_cost_mean", "label": "K=10"}}]},
            {"id": 8, "claim": "UR5", "paper": "p", "checks": [{"kind": "solves", "experiment": "fig3", "method": "sdp"}],
             "not_run": "fig3: 92 h on 2 workers"}]}))
    r = runner.invoke(app, ["report", "--runs", "runs/ablation_k", "--out", "results/ablation_k",
                            "--experiment", "ablation_k", "--ledger", "results/PAPER.md"])
    assert r.exit_code == 0, r.output
    text = (tmp_path / "results" / "PAPER.md").read_text()
    assert "SDP at K 5: cost 16 ± 0.98 (2 seeds)" in text and "K=5 16 ± 0.98 (2 seeds) vs K=10 15.5 ± 0.98 (2 seeds)" in text
    assert "| 12 | K = 5 diffusion steps suffice |" in text and "**reproduced** |" in text   # 16 <= 1.1 x 15.5
    assert "**not run** |" in text and "fig3: 92 h on 2 workers" in text
    assert "[ablation_k](ablation_k/README.md)" in text
    # the report draws the K variants apart (all_runs.csv keeps the plain method)
    out = tmp_path / "results" / "ablation_k"
    assert set(pd.read_csv(out / "all_runs.csv").method) == {"sdp"}
    assert set(pd.read_csv(out / "fig1_pendulum.csv").method) == {"sdp-K2", "sdp-K5", "sdp-K10"}
    from sdp_cli.report.figures.style import method_order   # legends list K in numeric order
    from sdp_cli.report.rows import Variant

    assert sorted([Variant("sdp", k=10), "sdp", Variant("sdp", k=2), "dp", Variant("sdp", k=5)], key=method_order) == [
        "dp", "sdp", "sdp-K2", "sdp-K5", "sdp-K10"]
    k = pd.read_csv(out / "ablation_k_pendulum.csv")
    assert list(k[k.quantity == "policy cost"].sort_values("k_rollout")["mean"]) == [30.5, 16.0, 15.5]
    assert (out / "ablation_k_pendulum.png").stat().st_size > 10_000
    from sdp_cli.report.figures.style import COLORS, MARKERS

    from matplotlib.colors import to_rgb

    assert len({COLORS.get(Variant("sdp", k=k)) for k in (2, 5, 10)}) == 3 and to_rgb(COLORS.get(Variant("sdp", k=5))) == to_rgb("tab:red")
    assert MARKERS.get(Variant("dp", k=2)) == "s" and COLORS.get("unknown") is None

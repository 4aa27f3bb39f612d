"""The claims' rules: our number and a verdict per claim of the paper, from report tables.

Each rule takes ``res`` (``{experiment: all_runs.csv rows, "bench/<name>": bench CSV}``, see
:func:`sdp_cli.report.ledger.load_results`) and ``p``, the claim's ``params`` from results/claims.yaml
over its top-level ``rules`` (the paper's numbers, thresholds, tasks and loops live there, never here),
and returns a :class:`Row`. A rule reads the reports; the judging is the verdict kinds' of
:mod:`sdp_cli.report.ledger.kinds` (a ratio per seed within one evaluation, a cost within a share of another,
the first dataset size from which a cost is reached, a share at least a line) and the generic combinations of
:mod:`sdp_cli.report.ledger.verdicts`: means over seeds with 95% intervals, "solves" at ``p["solved"]``
success, runs that have not reached their task's final iteration left out and named. A claim names its rule
in the yaml (``rule:``); :data:`RULES` holds them by name.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from sdp_cli.report.ledger.kinds import AtLeast, Ratio, Within
from sdp_cli.report.ledger.rules_fig1 import dp_needs_more, mlp_unstable, pendulum_torque, sdp_reaches_to
from sdp_cli.report.rows import conversion_text, last_iteration, loop_t_a, method_label, per_seed, unfinished
from sdp_cli.report.ledger.verdicts import VERDICTS, Row, all_any, combine, distance_text, fmt, pct_text, ratio_verdict

__all__ = ["RULES", "VERDICTS", "Row", "combine", "fmt", "ratio_verdict"]


# ---------------------------------------------------------------------------- the claims' numbers
def loop_to(p) -> str:
    """How a rule names the loop's TO (``to_alone_*``, ``refined_*``): its family's solver (``loop_to`` of the
    claim's parameters, set by the ledger per TO family), fatrop's multiple shooting by default."""
    return p.get("loop_to", "multiple shooting")


def fig2_only_sdp(res, p) -> Row:
    d = res["fig2"]
    last = last_iteration(d)
    parts, solved = [], {}
    for m in ("sdp", "dp", "pddp", "pddp_s"):
        g = last[last.method == m]
        if g.empty:
            parts.append(f"{method_label(m)}: " + ("not finished" if (d.method == m).any() else "not run"))
            continue
        sr = per_seed(g, "success_rate")
        solved[m] = AtLeast(sr.mean(), p["solved"]).holds
        parts.append(f"{method_label(m)} {fmt(per_seed(g, 'policy_cost_mean'))}, success {fmt(sr, pct=True)}"
                     + distance_text(g))
    sdp = loop_t_a(d[d.method == "sdp"])
    near = ""
    k = p["near_iteration"] - 1
    if not sdp.empty and (sdp.iteration >= k).any():
        it3 = per_seed(sdp[sdp.iteration == k], "policy_cost_mean")
        ref = per_seed(last[last.method == "sdp"], "refined_cost_mean")
        near_k = Within(it3.mean(), ref.mean(), p["within"])
        near_ok = near_k.holds
        near = f"; SDP after {p['near_iteration']} iterations {fmt(it3)} vs its final refined {fmt(ref)} ({near_k.text()})"
    else:
        near_ok = False
    others = [m for m in ("dp", "pddp", "pddp_s") if m in solved]
    if not solved.get("sdp"):
        verdict = "not reproduced"
    elif any(solved[m] for m in others):
        verdict = "partly"
    else:
        verdict = "reproduced" if (len(others) == 3 and near_ok) else "partly"
    missing = [m for m in ("dp", "pddp", "pddp_s") if m not in solved]
    detail = "; ".join(x for x in (f"methods without a finished run yet: {', '.join(map(method_label, missing))}" if missing else "",
                                   unfinished(d)) if x)
    return Row("; ".join(parts) + near, verdict, detail)


def fig2_to_alone(res, p) -> Row:
    last = last_iteration(res["fig2"])
    sdp = last[last.method == "sdp"]
    fail_ms = 1 - sdp.to_alone_converged_rate.mean()
    fail_ss = 1 - sdp.ss_to_alone_converged_rate.mean() if "ss_to_alone_converged_rate" in sdp else np.nan
    it_ms = per_seed(sdp, "refined_iterations_mean")
    it_ss = per_seed(sdp, "ss_refined_iterations_mean") if "ss_refined_iterations_mean" in sdp else pd.Series(dtype=float)
    ours = (f"TO alone fails {100 * fail_ms:.0f}% ({loop_to(p)}, {sdp.to_alone_iterations_mean.mean():.0f} it.), "
            f"{100 * fail_ss:.0f}% (single shooting, {sdp.ss_to_alone_iterations_mean.mean():.0f} it.); "
            f"refining the final SDP: {fmt(it_ms)} it. ({loop_to(p)}), {fmt(it_ss)} it. (single shooting)")
    ours += (f"; cost: TO alone {sdp.to_alone_cost_mean.mean():.3g} ({loop_to(p)}), "
             f"{sdp.ss_to_alone_cost_mean.mean():.3g} (single shooting), refined from the final SDP "
             f"{fmt(per_seed(sdp, 'refined_cost_mean'))}")
    if "to_alone_success_rate" in sdp and sdp.to_alone_success_rate.notna().any():   # converged is not solved
        ours += (f"; reaching the goal: TO alone {100 * sdp.to_alone_success_rate.mean():.0f}% ({loop_to(p)}), "
                 f"refined from the final SDP {fmt(per_seed(sdp, 'refined_success_rate'), pct=True)}")
    hits = [AtLeast(f, p["fail_rate"]).holds for f in (fail_ms, fail_ss) if np.isfinite(f)]
    verdict = "reproduced" if hits and all(hits) else "partly" if any(hits) else "not reproduced"
    return Row(ours, verdict, unfinished(res["fig2"]))


def table2c(res, p) -> Row:
    """Claim 7 (Table 2c): the final SDP's T_a sweep. The speed-up at the smallest T_a divides each T_a-1 row's
    own TO-alone time by its refine time (one evaluation; per seed, then the mean); the degradation divides the
    worst mean policy cost at T_a >= ``degraded_t_a_min`` by the worst at T_a <= ``best_t_a_max``, the paper's
    137 / 33.5."""
    d = res["fig2"]
    d = d[(d.method == "sdp") & (d.iteration == d[d.method == "sdp"].iteration.max())]
    if d.t_a.nunique() < 3:
        return Row("T_a sweep not run yet", "not run")
    by = d.groupby("t_a")
    solve = by.refined_solve_time_mean.mean()
    ss_solve = by.ss_refined_solve_time_mean.mean() if "ss_refined_solve_time_mean" in d else solve * np.nan
    roll = by.rollout_time_per_instance.mean()
    cost = by.policy_cost_mean.mean()
    t1 = min(solve.index)
    d1 = d[d.t_a == t1]
    to_ms, to_ss = d1.to_alone_solve_time_mean.mean(), d1.ss_to_alone_solve_time_mean.mean()
    paper = p["speedup"][0] / p["speedup"][1]
    r_ms, r_ss = (Ratio.of(d1, f"{pre}to_alone_solve_time_mean", f"{pre}refined_solve_time_mean", paper, p["keep"],
                           p["partly"], name) for pre, name in (("", loop_to(p)), ("ss_", "single shooting")))
    best, worse, mid = p["best_t_a_max"], p["degraded_t_a_min"], p["trade_off_t_a"]
    lo = cost[cost.index <= best].max()
    hi = cost[cost.index >= worse]
    degr = hi.max() / lo if len(hi) else np.nan
    t9 = mid if mid in roll.index else roll.index[np.argmin(abs(roll.index - mid))]
    ours = (f"T_a {t1}: refine {solve[t1]:.3g} s vs TO alone {to_ms:.3g} s ({r_ms.text()}), "
            f"{ss_solve[t1]:.3g} s vs {to_ss:.3g} s ({r_ss.text()}); T_a {t9}: rollout "
            f"{roll[t9]:.3g} s, solve {solve[t9]:.3g} s / {ss_solve[t9]:.3g} s; policy cost at T_a >= {worse}: "
            + ", ".join(f"{c:.3g}" for c in hi) + f" vs worst {lo:.3g} at T_a <= {best} ({degr:.2f}x)")
    v = [r_ss.verdict, ratio_verdict(degr, p["degradation"][0] / p["degradation"][1], p["keep"], p["partly"])]
    verdict = combine(v)
    return Row(ours, verdict, f"speed-up verdict (single shooting): {v[0]}; "
                              f"degradation verdict: {v[1]}; times are per instance on our CPU")


def speedup(res, p) -> Row:
    """Claim 13: per experiment and loop, TO alone's solve time over TO's from the final SDP's rollouts at the
    loop's T_a, each ratio within one evaluation (a row), per seed, then the mean (:class:`Ratio`)."""
    parts, verdicts = [], []
    for exp in p["experiments"]:
        if exp not in res:
            continue
        last = last_iteration(res[exp])
        last = loop_t_a(last[last.method == "sdp"])
        # Fig. 3 runs one loop per (T_h, T_a): a ratio per loop, not pooled over them
        keys = ["task", "horizon", "t_a"] if {"horizon", "t_a"} <= set(last.columns) else ["task"]
        if "horizon" in keys:   # rows evaluated before T_h was recorded: the task's one T_h, if it has one
            one = last.groupby("task").horizon.transform(lambda h: h.dropna().iloc[0] if h.nunique() == 1 else np.nan)
            last = last.assign(horizon=last.horizon.fillna(one))
        for key, sdp in last.groupby(keys, dropna=False):
            task, *loop = key if isinstance(key, tuple) else (key,)
            several = len(loop) and last[last.task == task].groupby(keys[1:], dropna=False).ngroups > 1
            where = f"{task} (T_h {loop[0]:g}, T_a {loop[1]:g})" if several else task
            for name, to, ref in ((loop_to(p), "to_alone_solve_time_mean", "refined_solve_time_mean"),
                                  ("single shooting", "ss_to_alone_solve_time_mean", "ss_refined_solve_time_mean")):
                if ref not in sdp or sdp[ref].isna().all():
                    continue
                r = Ratio.of(sdp, to, ref, p["ratio"], p["keep"], p["partly"], f"{exp} {where} {name}")
                parts.append(r.text())
                verdicts.append(r.verdict)
    if not parts:
        return Row("", "not run")
    verdict = combine(verdicts)
    return Row("; ".join(parts), verdict, "; ".join(x for x in (unfinished(res[e]) for e in p["experiments"]
                                                                if e in res) if x))


def epoch_cost(res, p) -> Row:
    b = res["bench/train_step"]
    b = b[b["mode"] == "sdp-jvp"]
    if b.empty:
        return Row("", "not run", "results/bench/train_step.csv has no sdp-jvp row")
    ok = [abs(r - p["ratio"]) <= p["tolerance"] for r in b.cpu_ratio_to_dp]
    ours = "; ".join(f"{r.cpu_ratio_to_dp:.2f} ({r.setting}, load {r.load})" for r in b.itertuples())
    return Row(f"SDP step / DP step, CPU time: {ours}", all_any(ok), "bench/train_step.py, DP and SDP steps interleaved in one run, 1 thread; "
               "an epoch is the same number of steps for both, so the step ratio is the epoch ratio")


def k_steps(res, p) -> Row:
    d = res["ablation_k"]
    d = d[d.epochs == d.epochs.max()]
    parts, means = [], {}
    for k, g in d.groupby("k_rollout"):
        means[int(k)] = g.policy_cost_mean.mean()
        parts.append(f"K={int(k)}: {fmt(per_seed(g, 'policy_cost_mean'))}, success "
                     f"{fmt(per_seed(g, 'success_rate'), pct=True)}" + distance_text(g))
    to = d.to_alone_cost_mean.mean()
    k, ref = p["k"], p["reference_k"]
    if k not in means or ref not in means:
        return Row("; ".join(parts), "partly", f"K={k} or K={ref} missing")
    verdict = "reproduced" if Within(means[k], means[ref], p["within"]).holds else "not reproduced"
    return Row("; ".join(parts) + f" (TO alone {to:.3g}; {int(d.epochs.max())} epochs, n_traj 10)", verdict,
               f"rule: K={k} within {pct_text(p['within'])} of K={ref}'s mean cost")


def quadrotor_precision(res, p) -> Row:
    """Claim 9 (Fig. 4): per quadrotor layout, success (reaching the target) and the share of rollouts
    that break a constraint (obstacles, floor, ceiling; and an obstacle alone where the rows have
    ``obstacles_violation_rate``), SDP vs DP, at the last iteration."""
    last = last_iteration(res["fig4"])
    parts, ok, both = [], [], set()
    for task in sorted(t for t in last.task.unique() if str(t).startswith("quadrotor")):
        g = last[last.task == task]
        by = {m: g[g.method == m] for m in ("sdp", "dp") if (g.method == m).any()}
        if not by:
            continue
        s = {m: per_seed(x, "success_rate").mean() for m, x in by.items()}
        v = {m: per_seed(x, "violation_rate").mean() for m, x in by.items()}
        dist = {m: x.goal_distance_median.median() for m, x in by.items()}
        o = ({m: per_seed(x, "obstacles_violation_rate").mean() for m, x in by.items()}
             if "obstacles_violation_rate" in g and g.obstacles_violation_rate.notna().any() else None)

        def vs(d, fmt):   # "SDP x vs DP y", or one method's value where the other was not run
            return " vs ".join(f"{method_label(m)} {fmt(d[m])}" for m in ("sdp", "dp") if m in d)
        pct = lambda x: f"{100 * x:.0f}%"  # noqa: E731
        hit = f" (an obstacle: {vs(o, pct)})" if o else ""
        started = set(res["fig4"][res["fig4"].task == task].method)      # a loop partway is named as such
        missing = "".join(f"; {method_label(m)} {'not finished' if m in started else 'not run yet'}"
                          for m in ("sdp", "dp") if m not in by)
        parts.append(f"{task}{conversion_text(g[g.method.isin(['sdp', 'dp'])])}: success {vs(s, pct)}, constraint violated {vs(v, pct)}{hit}, final distance "
                     f"{vs(dist, lambda x: f'{x:.2g} m')}{missing}")
        if not missing:
            both.add(task)
            ok.append(AtLeast(s["sdp"], p["solved"]).holds and s["sdp"] > s["dp"]
                      and (task in p["obstacle_free"] or v["dp"] >= v["sdp"]))
    layouts = set(p["layouts"])
    full = layouts <= both
    verdict = ("reproduced" if ok and all(ok) and full else "partly" if any(ok) else "not reproduced")
    return Row("; ".join(parts), verdict, "; ".join(x for x in (
        "" if full else "layouts without both SDP and DP yet: " + ", ".join(sorted(layouts - both)),
        unfinished(res["fig4"]), f"rule: SDP solves (>= {pct_text(p['solved'])}), beats DP, and violates constraints "
                                 "no more often") if x))


def quadrotor9_times(res, p) -> Row:
    """Claim 10: quadrotor-9, mean TO solve time from the naive guess vs from the final SDP's and DP's rollouts."""
    last = last_iteration(res["fig4"])
    q = last[last.task == p["task"]]
    runs = res["fig4"][res["fig4"].task == p["task"]]
    todo = unfinished(runs)
    if q.empty or (not (q.method == "sdp").any() and (runs.method == "sdp").any()):
        # SDP's loop partway: both at the latest iteration both reached, and DP's final times where it finished
        dp = q[q.method == "dp"]
        final = (f"; DP at its final iteration {dp.iteration.max() + 1:g}: TO alone "
                 f"{dp.to_alone_solve_time_mean.mean():.3g} s, from DP {dp.refined_solve_time_mean.mean():.3g} s"
                 if len(dp) else "")
        return Row(_q9_partway(runs, loop_to(p)) + final, "not run", todo or f"{p['task']} not run yet")
    parts, verdicts = [], []
    alone, warm = p["paper_times"]
    for name, pre in ((loop_to(p), ""), ("single shooting", "ss_")):
        col = f"{pre}refined_solve_time_mean"
        if col not in q or q[col].isna().all():
            continue
        t = {m: q[q.method == m] for m in ("sdp", "dp") if (q.method == m).any()}
        text = lambda g: (f"TO alone {g[f'{pre}to_alone_solve_time_mean'].mean():.3g} s, from {method_label(g.method.iloc[0])} "   # noqa: E731
                          f"{g[col].mean():.3g} s")
        part = f"{name}: " + "; ".join(f"{method_label(m)}'s evaluation: {text(g)}" for m, g in t.items())
        if "sdp" in t:    # TO alone and from SDP timed within the SDP loop's own evaluation
            r = Ratio.of(t["sdp"], f"{pre}to_alone_solve_time_mean", col, alone / warm, p["keep"], p["partly"],
                         "TO alone / from SDP")
            part += f" ({r.text()})"
            verdicts.append(r.verdict)
        parts.append(part)
    verdict = combine(verdicts) if verdicts else "not run"   # DP alone says nothing of the claim
    return Row("; ".join(parts), verdict, "; ".join(x for x in (
        todo, f"rule: TO alone / from SDP, both timed in the SDP loop's evaluation, against the paper's "
              f"{alone:g} / {warm:g} = {alone / warm:.1f}x, per baseline") if x))


def _q9_partway(d: pd.DataFrame, loop_to: str = "multiple shooting") -> str:
    """Claim 10's quantities at the latest iteration both SDP and DP reached, for loops not finished:
    shown beside the verdict "not run", never judged (the claim is about the final policies)."""
    if d.empty or not {"sdp", "dp"} <= set(d.method):
        return ""
    d = loop_t_a(d)
    it = int(min(d[d.method == m].iteration.max() for m in ("sdp", "dp")))
    g = d[d.iteration == it]
    t = {m: g[g.method == m] for m in ("sdp", "dp")}
    pct = lambda v: f"{100 * v:.0f}%"   # noqa: E731
    n_algo = f" of {d.n_algo.max():g}" if "n_algo" in d and d.n_algo.notna().any() else ""
    return (f"partway, not judged: iteration {it + 1}{n_algo} (the latest both reached), {loop_to}: "
            f"TO alone {g.to_alone_solve_time_mean.mean():.3g} s, from SDP {t['sdp'].refined_solve_time_mean.mean():.3g} s, "
            f"from DP {t['dp'].refined_solve_time_mean.mean():.3g} s; converged: TO alone "
            f"{pct(g.to_alone_converged_rate.mean())}, from SDP {pct(t['sdp'].refined_converged_rate.mean())}, "
            f"from DP {pct(t['dp'].refined_converged_rate.mean())}")


def ur5_long_actions(res, p) -> Row:
    """Claim 8 (Fig. 3): per UR5 variant and (T_h, T_a), SDP's success at the last iteration, and the
    TO iterations and cost from SDP's guess against TO alone; DP's beside it where it ran. "not run"
    until SDP has reached the last iteration (DP's numbers alone say nothing of the claim)."""
    last = last_iteration(res["fig3"])
    it = f"iteration {last.iteration.max() + 1:g}" if len(last) else ""
    todo = unfinished(res["fig3"])

    def part(g) -> str:
        return (f"success {100 * per_seed(g, 'success_rate').mean():.0f}%, TO iterations "
                f"{g.refined_iterations_mean.mean():.3g} vs {g.to_alone_iterations_mean.mean():.3g} alone, "
                f"cost {g.refined_cost_mean.mean():.3g} vs {g.to_alone_cost_mean.mean():.3g}")

    loops = {k: g for k, g in last.groupby(["task", "horizon", "t_a"])}
    sdp = last[last.method == "sdp"]
    if sdp.empty:
        dp = "; ".join(f"{task} (T_h {h:g}, T_a {t_a:g}) DP at {it}: {part(g[g.method == 'dp'])}"
                       for (task, h, t_a), g in loops.items() if (g.method == "dp").any())
        started = (res["fig3"].method == "sdp").any()     # then named among the unfinished runs
        return Row(dp, "not run", "; ".join(x for x in ("" if started else "SDP not run yet", todo) if x))
    parts, ok = [], []
    for (task, h, t_a), g in loops.items():
        s, dp = g[g.method == "sdp"], g[g.method == "dp"]
        if s.empty:
            begun = (task, int(h), int(t_a)) in _sdp_loops(res["fig3"])
            parts.append(f"{task} (T_h {h:g}, T_a {t_a:g}): SDP {'not finished' if begun else 'not run yet'}, "
                         f"DP {part(dp)}")
            continue
        rate = per_seed(s, "success_rate").mean()
        faster = s.refined_iterations_mean.mean() < s.to_alone_iterations_mean.mean()
        better = s.refined_cost_mean.mean() <= s.to_alone_cost_mean.mean()
        ok.append(AtLeast(rate, p["solved"]).holds and faster and better)
        parts.append(f"{task} (T_h {h:g}, T_a {t_a:g}) at {it}: SDP {part(s)}" + (f"; DP {part(dp)}" if len(dp) else ""))
    full = set(p["t_a"]) <= set(sdp.t_a.astype(int)) and sdp.task.nunique() >= len(p["tasks"])
    verdict = all_any(ok, complete=full)
    loops = tuple((task, h, t_a) for task in p["tasks"] for h, t_a in p["loops"])
    return Row(" | ".join(parts), verdict, "; ".join(
        x for x in (_fig3_not_run(res["fig3"], loops, res.get("estimates/fig3")), todo) if x))


def _sdp_loops(d: pd.DataFrame) -> set[tuple[str, int, int]]:
    """(task, T_h, T_a) of the loops with an SDP row in ``d``, finished or not."""
    sdp = d[d.method == "sdp"]
    return set(zip(sdp.task, sdp.horizon.astype(int), sdp.t_a.astype(int)))


def _fig3_not_run(d: pd.DataFrame, loops: tuple, est: pd.DataFrame | None = None) -> str:
    """``"SDP not run on ..."``: Fig. 3's ``loops`` ``(task, T_h, T_a)`` without an SDP row, per task as
    ``(T_h, T_a)`` pairs; with
    ``est`` (the saved ``sdp pipeline fig3 --estimate`` table), each with the estimated hours of its runs
    that have no row in ``d`` (SDP's and DP's where neither ran)."""
    ran = _sdp_loops(d)
    todo = {}
    for task, h, t_a in loops:
        if (task, h, t_a) not in ran:
            todo.setdefault(task, []).append(f"({h}, {t_a})" + _loop_hours(est, d, task, h, t_a))
    if not todo:
        return ""
    hours = (" (hours: the loop's runs not made, `sdp pipeline fig3 --estimate` in one process on the CPU, "
             "results/estimates/fig3.txt)" if est is not None and len(est) else "")
    return "SDP not run on Fig. 3's (T_h, T_a) " + "; ".join(f"{t} {', '.join(p)}" for t, p in todo.items()) + hours


def _loop_hours(est: pd.DataFrame | None, d: pd.DataFrame, task: str, h: int, t_a: int) -> str:
    """``" 7.5 h"``: the estimated hours of loop ``(task, h, t_a)``'s runs without a row in ``d``
    (run names end in ``-h<T_h>-ta<T_a>``, :func:`sdp_cli.experiments.experiment.group_run_names`); ``""`` without."""
    if est is None or est.empty:
        return ""
    mine = est[(est.task == task) & est.run.str.endswith(f"-h{h}-ta{t_a}") & ~est.run.isin(set(d.get("run", ())))]
    return f" {mine.total_cpu_h.sum():.1f} h" if len(mine) else ""


#: every rule by the name results/claims.yaml gives it (``rule:``)
RULES = {fn.__name__: fn for fn in (sdp_reaches_to, dp_needs_more, pendulum_torque, mlp_unstable, fig2_only_sdp,
                                     fig2_to_alone, table2c, ur5_long_actions, quadrotor_precision, quadrotor9_times,
                                     epoch_cost, k_steps, speedup)}

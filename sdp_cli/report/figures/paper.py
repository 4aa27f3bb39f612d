"""The paper's figures and tables, one function per figure: ``fn(df, task, out) -> [written paths]``
over the rows of :func:`sdp_cli.report.runs.load_runs` (see :mod:`sdp_cli.report.make` for the list).
Artifacts are opened only through the paths the evaluation manifests name (``rollouts``, ``refined``).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.families import DEFAULT_TO
from sdp_cli.data.artifacts import load_npz
from sdp_cli.report.rows import TO_FAMILIES, family_of, loop_t_a, mean_ci, method_label, typed_like
from sdp_cli.report.figures.style import (COLORS, CURVE_STYLES, MARKERS, by_method, log_ticks, method_order,
                                  pyplot, save_csv, save_fig, save_md)

DIVERGED = 1e5
def _agg(df: pd.DataFrame, by: list[str], col: str) -> pd.DataFrame:
    rows = []
    for key, g in df.groupby(by, dropna=False):
        m, h, n = mean_ci(g[col])
        rows.append({**dict(zip(by, key if isinstance(key, tuple) else (key,))), "mean": m, "ci95": h, "n_seeds": n})
    return pd.DataFrame(rows)


def _bottom_room(tab: pd.DataFrame) -> float:
    """How far below the lowest mean a log axis starts: further (a free band for "≤0") where an interval of
    ``tab`` (``mean``, ``ci95``) reaches below zero."""
    ok = np.isfinite(tab["mean"]) & (tab["mean"] < DIVERGED) & np.isfinite(tab["ci95"].astype(float))
    return 6.0 if (tab["mean"][ok] - tab["ci95"][ok].astype(float) <= 0).any() else 1.5


def _mark_reaching_zero(ax, x, mean, ci, color, row: int = 0) -> None:
    """On a log axis an interval whose lower end is <= 0 runs off the bottom: write "≤0" there, at ``x``, in
    text row ``row`` (0 or 1) from the bottom; neighbouring curves alternate rows, so that none covers another."""
    for xi, m, h in zip(x, mean, ci):
        if ax.get_yscale() == "log" and np.isfinite(h) and m - h <= 0:
            ax.annotate("≤0", (xi, 0), xycoords=("data", "axes fraction"), xytext=(0, 2 + 9 * row),
                        textcoords="offset points", ha="center", va="bottom", fontsize=7, color=color)


def fig1(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """Fig. 1: the paper's quantity, the mean policy cost per dataset size (∞ where one diverged rollout
    made the mean infinite), and beside it the policy's success rate, which the mean hides then.
    One curve per (method, epochs), shifted a little along n_traj so that equal values stay visible; a task
    run with two TO families draws one row of panels per family (same axes), each with its TO-alone line."""
    d = df[(df.task == task) & (df.iteration == 0)]
    if d.empty or d["n_traj"].isna().all():
        return []
    by = ["method", "epochs", "n_traj"]
    tab = by_method(_agg(d, by, "policy_cost_mean"), by[1:])
    if "success_rate" in d:
        succ = _agg(d, by, "success_rate").rename(columns={"mean": "success_mean", "ci95": "success_ci95"})
        tab = tab.merge(succ.drop(columns="n_seeds"), on=by, how="left")
    to_by = _to_alone_by_family(d)      # one TO-alone line per TO family of the drawn runs
    tab["to_alone_mean"] = tab.method.map(family_of).map(to_by).astype(float)
    tos = [v for v in to_by.values() if np.isfinite(v)]
    finite = tab["mean"][np.isfinite(tab["mean"]) & (tab["mean"] < DIVERGED)]
    high = max(float(finite.max()) if len(finite) else 1.0, max(tos, default=0))
    low = min(float(finite.min()) if len(finite) else high, min(tos, default=high))
    # one outlier flattens the rest on a linear axis: log from a 30x spread (UR5: a 540 beside 6.4-16, where
    # the claim is read, drew them as one line at 300x)
    log_y = low > 0 and high * 1.3 / low > 30
    top = high * (4 if log_y else 1.3)   # the ∞ rows: a band above every mean (a factor 1.3 is 0.1 decade)
    families = sorted(set(tab.method.map(family_of)), key=lambda f: (f != DEFAULT_TO, f))
    plt = pyplot()
    fig, axes = plt.subplots(len(families), 2, figsize=(10, 4 * len(families)), squeeze=False,
                             gridspec_kw={"width_ratios": [3, 2]})
    for (ax, ax2), f in zip(axes, families):
        _fig1_row(ax, ax2, tab[tab.method.map(family_of) == f], log_y, top)
        v = to_by.get(f, np.nan)
        if np.isfinite(v):
            ax.axhline(v, color="black", ls=":", label="TO alone" + (f" ({TO_FAMILIES.get(f, f)})" if len(to_by) > 1 else ""))
        ax.set_ylim(*((low / _bottom_room(tab), top * 1.05) if log_y else (0, top * 1.05)))
        which = f", TO {TO_FAMILIES.get(f, f)}" if len(families) > 1 else ""
        ax.set_title(f"Fig. 1 — sample efficiency, {task}{which}", fontsize=10)
        ax2.set_title("policy success rate" + which, fontsize=10)
        ax2.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="upper left",
                   bbox_to_anchor=(1.02, 1.0))   # beside the axes, never over the data
    fig.tight_layout()
    return [save_csv(tab, out / f"fig1_{task}.csv"), save_fig(fig, out / f"fig1_{task}.png")]


def _fig1_row(ax, ax2, tab: pd.DataFrame, log_y: bool, top: float) -> None:
    """One row of Fig. 1: ``tab``'s curves (cost, success rate) over n_traj, on axes scaled by the caller."""
    curves = sorted(tab.groupby(["method", "epochs"]), key=lambda c: (method_order(c[0][0]), c[0][1]))
    if log_y:
        ax.set_yscale("log")
    for i, ((method, epochs), g) in enumerate(curves):
        ls = "-" if epochs == tab[tab.method == method]["epochs"].max() else "--"
        shift = 1.07 ** (i - (len(curves) - 1) / 2)       # multiplicative: the n_traj axis is log
        kw = dict(ls=ls, marker=MARKERS.get(method, "o"), color=COLORS.get(method, among=tab.method), capsize=3,
                  label=f"{method_label(method)} ({epochs} ep.)")
        ok = np.isfinite(g["mean"]) & (g["mean"] < DIVERGED)
        ax.errorbar(g["n_traj"][ok] * shift, g["mean"][ok], yerr=g["ci95"][ok].fillna(0), **kw)
        _mark_reaching_zero(ax, g["n_traj"][ok] * shift, g["mean"][ok], g["ci95"][ok], kw["color"], row=i % 2)
        for n in g["n_traj"][~ok]:   # neighbouring curves' ∞ in alternate rows, so that none covers another
            ax.annotate("∞", (n * shift, top), xytext=(0, -9 * (i % 2)), textcoords="offset points",
                        ha="center", va="top", fontsize=11, color=kw["color"])
        if "success_mean" in g:
            ax2.errorbar(g["n_traj"] * shift, g["success_mean"], yerr=g["success_ci95"].fillna(0), **kw)
    n_all = tab["n_traj"].astype(float)
    from matplotlib.ticker import FixedLocator, NullFormatter, StrMethodFormatter

    for a in (ax, ax2):
        a.set_xscale("log")
        a.set_xlim(n_all.min() / 1.5, n_all.max() * 1.5)  # also when every mean diverged (no point drawn)
        a.xaxis.set_major_locator(FixedLocator(sorted(set(n_all))))     # the dataset sizes run
        a.xaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("n_traj (trajectories in the dataset)")
    ax.set_ylabel("mean cost on test instances (∞: mean > 1e5)")
    ax2.set_ylim(-0.03, 1.03)
    ax2.set_ylabel("share of policy rollouts reaching the goal")


def budget_title(d: pd.DataFrame) -> str:
    """``", n_traj 30, 2000 epochs"`` when the rows share one budget, ``", n_traj 50, 50, 100 by iteration,
    ..."`` when they share a schedule that grows (Fig. 3), else ``", largest budget per method"``
    (:func:`sdp_cli.report.make.largest_budget`); empty without those columns."""
    if d.empty or not {"epochs", "n_traj", "iteration"} <= set(d.columns):
        return ""
    per_it = d.groupby("iteration").n_traj.agg(lambda s: tuple(s.dropna().unique()))
    e = d.epochs.dropna().unique()
    if len(e) == 1 and all(len(n) == 1 for n in per_it):
        sched = [n[0] for n in per_it]
        n = f"{sched[0]:g}" if len(set(sched)) == 1 else ", ".join(f"{v:g}" for v in sched) + " by iteration"
        return f", n_traj {n}, {e[0]:g} epochs"
    return ", largest budget per method"


def fig2a(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """Mean cost per loop iteration (policy; refined = TO warm-started by the policy, over its
    converged solves; ArgminCost(refined, TO alone), drawn dotted beside them since it is <= TO
    alone by construction; log scale, ∞ where the mean diverged) and the policy's success rate."""
    d = df[df.task == task]
    if d.empty:
        return []
    d = loop_t_a(d)
    rows = []
    for col, what in (("policy_cost_mean", "policy"), ("refined_cost_mean", "refined"),
                      ("argmin_cost_mean", "ArgminCost"), ("success_rate", "policy success rate")):
        if col in d:
            t = _agg(d, ["method", "iteration"], col)
            t["curve"] = what
            rows.append(t)
    tab = pd.concat(rows, ignore_index=True)
    plt = pyplot()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4), gridspec_kw={"width_ratios": [3, 2]})
    costs = tab[tab.curve != "policy success rate"]
    finite = costs["mean"][np.isfinite(costs["mean"]) & (costs["mean"] < DIVERGED)]
    to_by = _to_alone_by_family(d)
    if len(to_by) > 1:      # TO families drawn apart: their TO alone in the table too
        tab = pd.concat([tab, pd.DataFrame([{"method": f"to-{f}", "iteration": np.nan, "mean": v, "ci95": np.nan,
                                             "n_seeds": np.nan, "curve": "TO alone"} for f, v in to_by.items()])],
                        ignore_index=True)
        costs = tab[~tab.curve.isin(["policy success rate", "TO alone"])]
        tab_curves = tab[tab.curve != "TO alone"]
    else:
        tab_curves = tab
    tos = [v for v in to_by.values() if np.isfinite(v)]
    to = tos[0] if len(to_by) == 1 and tos else np.nan
    lo = min(float(finite.min()) if len(finite) else 1.0, min(tos, default=np.inf)) / _bottom_room(costs)
    top = max(float(finite.max()) if len(finite) else 1.0, max(tos, default=0)) * 3
    methods = sorted(tab_curves.method.unique(), key=method_order)
    ax.set_yscale("log")
    for (method, curve), g in tab_curves.groupby(["method", "curve"]):
        g = g.sort_values("iteration")
        ok = np.isfinite(g["mean"]) & (g["mean"] < DIVERGED)
        a = ax2 if curve == "policy success rate" else ax
        # methods side by side around each iteration, so equal values (e.g. 0% success) stay visible
        shift = 0.06 * (methods.index(method) - (len(methods) - 1) / 2)
        a.errorbar(g["iteration"][ok] + shift, g["mean"][ok], yerr=g["ci95"][ok].fillna(0),
                   marker=MARKERS.get(method, "o"), capsize=3, ls=CURVE_STYLES.get(curve, "-"),
                   color=COLORS.get(method, among=methods),
                   mfc="white" if curve == "ArgminCost" else COLORS.get(method, among=methods))
        if a is ax:  # one ∞ per method and iteration, side by side
            _mark_reaching_zero(ax, g["iteration"][ok] + shift, g["mean"][ok], g["ci95"][ok],
                                COLORS.get(method, among=methods))
            for it in g["iteration"][~ok]:
                ax.annotate("∞", (it + shift, top), ha="center", va="top", fontsize=16,
                            color=COLORS.get(method, among=methods))
    if np.isfinite(to):
        ax.axhline(to, color="black", ls="-.", lw=1)
    family_lines = {f: ("black" if f == DEFAULT_TO else "0.55") for f in to_by} if len(to_by) > 1 else {}
    for f, v in to_by.items():
        if family_lines and np.isfinite(v):
            ax.axhline(v, color=family_lines[f], ls="-.", lw=1)
    # legends from explicit handles: colour and marker = method, line style = curve
    from matplotlib.lines import Line2D

    m_handles = [Line2D([], [], color=COLORS.get(m, among=methods), marker=MARKERS.get(m, "o"), ls="-",
                        label=method_label(m))
                 for m in methods]
    c_handles = [Line2D([], [], color="0.3", ls=CURVE_STYLES[c], lw=1.6,
                        label={"policy": "policy rollout", "refined": "refined (TO warm-started by the policy)",
                               "ArgminCost": "ArgminCost(refined, TO alone)"}[c])
                 for c in CURVE_STYLES if c in set(costs.curve)]
    if np.isfinite(to):
        c_handles.append(Line2D([], [], color="black", ls="-.", lw=1, label="TO alone (naive guess)"))
    c_handles += [Line2D([], [], color=c, ls="-.", lw=1, label=f"TO alone (naive guess, {TO_FAMILIES.get(f, f)})")
                  for f, c in family_lines.items()]
    iters = sorted(int(i) for i in tab_curves.iteration.unique())
    for a in (ax, ax2):
        a.set_xticks(iters)
        a.set_xlabel("algorithm iteration")
    ax.set_ylim(lo, top * 1.2)
    log_ticks(ax.yaxis, lo, top * 1.2)
    ax.set_ylabel("mean cost on test instances (∞: mean > 1e5)")
    ax.set_title(textwrap.fill(f"Fig. 2a — alternating loop, {task}{budget_title(d)}", 70), fontsize=10)
    ax2.set_ylim(-0.03, 1.03)
    ax2.set_ylabel("share of policy rollouts reaching the goal")
    ax2.set_title("policy success rate", fontsize=10)
    # beside the axes, never over the data: methods (colour, marker), then curves (line style)
    first = ax2.legend(handles=m_handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), title="method",
                       title_fontsize=7)
    ax2.add_artist(first)
    ax2.legend(handles=c_handles, fontsize=7, loc="lower left", bbox_to_anchor=(1.02, 0.0), title="cost curve",
               title_fontsize=7)
    fig.tight_layout()
    return [save_csv(tab, out / f"fig2a_{task}.csv"), save_fig(fig, out / f"fig2a_{task}.png")]


def _to_alone_by_family(d: pd.DataFrame) -> dict[str, float]:
    """Mean TO-alone cost per TO family of the drawn methods (one entry: the usual single line)."""
    if "to_alone_cost_mean" not in d:
        return {}
    fam = d.method.map(family_of)
    return {f: mean_ci(g["to_alone_cost_mean"])[0] for f, g in d.groupby(fam)}


def _named(path) -> Path | None:
    """A file a manifest names (``None``/NaN: none), if it is still there."""
    return Path(path) if isinstance(path, str) and path and Path(path).is_file() else None


def _to_alone_once(t: pd.DataFrame) -> pd.Series:
    """TO alone's iterations (rows with guess "naive") of one run: the solve is the same for every method and
    seed (the same test instances), so each run repeats it; rows without a run (older tables) are kept."""
    base = t[t.guess == "naive"]
    base = base[base.method == sorted(t.method.unique())[0]]
    runs = sorted(base.run.dropna().unique()) if "run" in base else []
    return (base[base.run == runs[0]] if runs else base).iterations


def fig2b(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """Histogram of TO iterations at the last iteration, at the loop's T_a: TO alone (naive
    guess) vs warm-started by each method's policy (instances whose rollout diverged are no guess), as
    shares of each one's solves (methods pool different numbers of runs; TO alone is one run's);
    one panel per TO the runs evaluated (the loop's: fatrop's multiple shooting or box-FDDP; single shooting, the
    IPOPT baseline). ``carried``
    (:class:`~sdp_cli.report.carry.Carried`): the earlier report's rows of runs whose files are gone."""
    d = df[df.task == task]
    if d.empty:
        return []
    last = loop_t_a(d)
    last = last[last.iteration == last.iteration.max()]
    t_a = {m: ",".join(str(int(v)) for v in sorted(g.dropna().unique())) for m, g in last.groupby("method").t_a}
    several = last.t_a.dropna().nunique() > 1     # the MLPs act one step at a time, the diffusion policies T_a

    def ta_of(method: str) -> str:
        """``"T_a 31, "`` where the drawn rows hold several T_a, else ``""`` (the title names the one)."""
        return f"T_a {t_a[method]}, " if several and t_a.get(method) else ""

    rows = []
    for r in last.itertuples():
        f = _named(r.refined)
        if f is None:
            continue
        a, _ = load_npz(f, kind="dataset")
        for solver, pre in (("multiple shooting", "inst_"), ("single shooting", "inst_ss_")):
            if pre + "pol_iterations" not in a:
                continue
            pi, bi = a[pre + "pol_iterations"], a[pre + "base_iterations"]
            rows += [{"solver": solver, "method": r.method, "guess": "policy", "iterations": int(v), "run": r.run}
                     for v in pi[pi >= 0]]
            rows += [{"solver": solver, "method": r.method, "guess": "naive", "iterations": int(v), "run": r.run}
                     for v in bi[bi >= 0]]
    old = carried.rows(f"fig2b_{task}.csv", task, last) if carried else pd.DataFrame()
    if not old.empty:
        old["method"] = typed_like(old.method, last.method)      # (their variants' parts, as drawn now)
    if not rows and old.empty:
        return []
    tab = pd.concat([pd.DataFrame(rows), old], ignore_index=True)
    fam = tab.method.map(family_of)
    loop_to = (tab.solver == "multiple shooting") & (fam != DEFAULT_TO)   # the loop's TO is another family's solver
    tab.loc[loop_to, "solver"] = fam[loop_to].map(lambda f: TO_FAMILIES.get(f, f))
    from matplotlib.lines import Line2D

    plt = pyplot()
    order = ["multiple shooting", *(v for k, v in TO_FAMILIES.items() if k != DEFAULT_TO), "single shooting"]
    solvers = [s for s in order if s in set(tab.solver)] + sorted(set(tab.solver) - set(order))
    fig, axes = plt.subplots(1, len(solvers), figsize=(6 * len(solvers), 4), squeeze=False)
    hi = max(int(tab.iterations.max()), 1)
    bins = np.unique(np.geomspace(1, hi + 1, 30).astype(int))
    lo_x, hi_x = max(0.8, tab.iterations.min() / 1.5), hi * 1.5
    for ax, solver in zip(axes[0], solvers):
        t = tab[tab.solver == solver]
        # TO alone once per panel: a loop-TO panel holds one family's runs; single shooting solves the same
        # instances whatever the loop's TO was
        f = min(t.method.map(family_of))
        base = _to_alone_once(t[t.method.map(family_of) == f])
        *_, base_patches = ax.hist(base, bins=bins, weights=np.full(len(base), 1 / max(len(base), 1)),
                                   histtype="stepfilled", color="0.85" if f == DEFAULT_TO else "0.65", edgecolor="0.4",
                                   lw=1.2, alpha=1 if f == DEFAULT_TO else 0.6,
                                   label=f"TO alone (naive guess, {len(base)} instances), mean {base.mean():.0f}")
        pol = t[t.guess == "policy"]
        groups = sorted(pol.groupby("method"), key=lambda x: method_order(x[0]))
        # outlines drawn widest first: where histograms coincide (every warm start at 8 iterations) each one's
        # edge still shows beside the narrower ones drawn over it
        handles = [base_patches[0]]   # hist puts its label on the first patch
        for (method, g), lw in zip(groups, outline_widths(len(groups))):
            color = COLORS.get(method, among=pol.method)
            label = f"warm-started by {method_label(method)}: {ta_of(method)}{len(g)} guesses, " \
                    f"mean {g.iterations.mean():.0f}"
            ax.hist(g.iterations, bins=bins, weights=np.full(len(g), 1 / len(g)), histtype="step", lw=lw,
                    color=color)
            handles.append(Line2D([], [], color=color, lw=lw, label=label))   # a line of the outline's width
        ax.set_xscale("log")
        ax.set_xlim(lo_x, hi_x)
        log_ticks(ax.xaxis, lo_x, hi_x)
        ax.set_xlabel(f"TO iterations, {solver}")
        ax.set_ylabel("share of solves")
        ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16),
                  frameon=False)   # below: no bar hidden
    one_t_a = "" if several or last.t_a.dropna().empty else f", T_a = {int(last.t_a.dropna().iloc[0])}"
    fig.suptitle(f"Fig. 2b — TO iterations, {task} (iteration {int(d.iteration.max())}{one_t_a}"
                 f"{budget_title(d)})", fontsize=10)
    return [save_csv(tab, out / f"fig2b_{task}.csv"), save_fig(fig, out / f"fig2b_{task}.png")]


def outline_widths(n: int, widest: float = 5.0, narrowest: float = 1.5) -> list[float]:
    """Line widths of ``n`` outlines drawn one over another, widest first, each one visibly wider than the next."""
    return list(np.linspace(widest, narrowest, n)) if n > 1 else [2.0] * n


TABLE2C = {"policy_cost_mean": "policy cost (mean)", "policy_cost_median": "policy cost (median)",
           "success_rate": "policy success rate", "refined_cost_mean": "refined cost (TO warm-started by the policy)",
           "refined_converged_rate": "refined converged", "argmin_cost_mean": "ArgminCost(refined, TO alone)",
           "refined_iterations_mean": "TO iterations warm-started by the policy", "rollout_time_per_instance": "rollout time (s)",
           "refined_solve_time_mean": "solving time (s)", "total_time": "total time (s)",
           "to_alone_cost_mean": "TO alone cost", "to_alone_iterations_mean": "TO alone iterations",
           "to_alone_solve_time_mean": "TO alone time (s)",
           # the single-shooting baseline (the paper's solver family), when the run evaluated it
           "ss_refined_cost_mean": "single shooting: refined cost", "ss_refined_iterations_mean": "single shooting: TO iterations warm-started",
           "ss_refined_solve_time_mean": "single shooting: solving time (s)", "ss_to_alone_cost_mean": "single shooting: TO alone cost",
           "ss_to_alone_converged_rate": "single shooting: TO alone converged",
           "ss_to_alone_iterations_mean": "single shooting: TO alone iterations", "ss_to_alone_solve_time_mean": "single shooting: TO alone time (s)"}


def table2c(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    d = df[(df.task == task)].copy()
    if d.empty or "refined_solve_time_mean" not in d:
        return []
    d = d[d.iteration == d.iteration.max()]
    d = d[d.epochs == d.groupby("method").epochs.transform("max")]     # per method (PDDP+S alone has 3e3 on UR5)
    d["total_time"] = d["rollout_time_per_instance"] + d["refined_solve_time_mean"]
    cols = [c for c in TABLE2C if c in d and d[c].notna().any()]
    tab = by_method(d.groupby(["method", "t_a"])[cols].mean().reset_index(), ["t_a"])
    tab = tab.rename(columns={"t_a": "T_a", **TABLE2C})
    return [save_csv(tab, out / f"table2c_{task}.csv"),
            save_md(tab, out / f"table2c_{task}.md", f"Table 2c — T_a trade-off, {task} (last iteration{budget_title(d)})")]


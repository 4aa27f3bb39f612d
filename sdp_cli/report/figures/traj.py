"""The report's trajectory figure, ``traj_<task>``: TO alone vs each method's policy and refined solution
on the first few test instances, each panel titled with every rollout's outcome (goal or miss, the
constraint groups it breaks) and the figure with the shares over all test instances.

A task evaluated under two TO families (``sdp loop --to ddp`` beside the main one) gets one figure per family
(:func:`traj_parts`): each family's TO alone is its own solver's, and one figure of both drew the first
method's family's TO alone for all (and 16 series in a panel)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.families import DEFAULT_TO
from sdp_cli.data.artifacts import load_npz
from sdp_cli.report.figures.paper import _named
from sdp_cli.report.rows import TO_FAMILIES, family_of, loop_t_a, method_label, split_family
from sdp_cli.report.figures.style import COLORS, method_order, pyplot, save_fig
from sdp_cli.tasks import get_task


def _best_rollout(d: pd.DataFrame):
    """(rollout path, refine path, run) of the best evaluated row of ``d`` whose manifest names
    both files."""
    d = d.sort_values(["success_rate", "policy_cost_median"], ascending=[False, True])
    for row in d.itertuples():
        ro, rf = _named(row.rollouts), _named(row.refined)
        if ro is not None and rf is not None:
            return ro, rf, f"{row.run}, iteration {row.iteration}"
    return None


def _last_iterations(d: pd.DataFrame) -> pd.DataFrame:
    """The rows of each method at the last iteration that method reached: a loop still running (one method
    ahead of the other) draws both, each at its own last iteration."""
    return d[d.iteration == d.groupby("method").iteration.transform("max")]


def _outcome(task, r: dict, j: int) -> str:
    """Rollout ``j``'s outcome in a few words: "goal" / "miss", then the constraint groups it breaks
    (beyond the evaluation's tolerance), e.g. "miss, breaks obstacles"."""
    from sdp_cli.algorithm.evaluate import VIOLATION_TOL

    viol = task.violations_per_instance(r["X"][j:j + 1], r["U"][j:j + 1], r["xi"][j:j + 1])
    broken = [g for g, v in viol.items() if not v[0] <= VIOLATION_TOL]
    return ("goal" if r["reached"][j] else "miss") + (f", breaks {'+'.join(broken)}" if broken else "")


def _shares(r: dict, meta: dict) -> str:
    """Over all test instances: the share reaching the goal, and breaking each constraint group that any breaks."""
    from sdp_cli.algorithm.evaluate import group_violation_rates

    rates = {k[:-len("_violation_rate")]: v for k, v in group_violation_rates(r, meta).items() if v > 0}
    return f"goal {np.mean(r['reached']):.0%}" + "".join(f", breaks {g} {v:.0%}" for g, v in rates.items())


def _refine_note(f: dict, j: int) -> str:
    """``", refine not converged"`` where TO from this policy's rollout did not converge on instance ``j``."""
    ok = f.get("inst_pol_converged")
    return ", refine not converged" if ok is not None and not bool(ok[j]) else ""


def line_widths(n: int, thinnest: float, step: float) -> list[float]:
    """Line widths of ``n`` series drawn in turn, widest first, ``step`` apart: each later line is thinner, so
    where two paths coincide the earlier one still shows on both sides of the one drawn over it (SDP's line hid
    PDDP+S's on quadrotor-0, both 1.4 wide)."""
    return [thinnest + step * (n - 1 - i) for i in range(n)]


def traj_parts(df: pd.DataFrame, task: str) -> list[tuple[str, pd.DataFrame]]:
    """``(file name, rows)`` of each trajectory figure of ``task``: one ``traj_<task>.png`` of all its rows,
    or, where its methods are drawn per TO family (``sdp-to-ddp``, :func:`~sdp_cli.report.rows.method_variants`),
    one per family: the main one's (``ms``) ``traj_<task>.png``, another's ``traj_<task>-to-<family>.png``."""
    d = df[df.task == task]
    fam = d.method.map(family_of)
    return [(f"traj_{task}.png" if f == DEFAULT_TO else f"traj_{task}-to-{f}.png", d[fam == f])
            for f in sorted(fam.unique(), key=lambda f: (f != DEFAULT_TO, f))]


def traj(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    """Each of :func:`traj_parts` drawn by :func:`trajectories`, or the earlier report's where some method it
    draws has only carried runs, whose rollouts are gone (``carried``: :class:`~sdp_cli.report.carry.Carried`)."""
    written = []
    for name, rows in traj_parts(df, task):
        if carried is not None and carried.kept_traj(rows, name):
            written.append(carried.out / name)      # the earlier report's file, kept where it is
        else:
            written += trajectories(rows, task, out, name=name)
    return written


def trajectories(df: pd.DataFrame, task_name: str, out: Path, n_show: int = 4, name: str | None = None) -> list[Path]:
    """TO alone vs each method's policy and refined solution on a few test instances (the best
    run of each method at the last iteration it reached; the test instances are the same for all), written to
    ``out / name`` (default ``traj_<task>.png``). ``df``'s rows are of one TO family, whose TO alone is drawn
    (:func:`traj_parts`); a family suffix of their methods is named once, in the title.

    Pendulums: the tip's distance to the goal over time, with the goal tolerance (their tip paths all lie
    on the same circle, which showed nothing); UR5 and quadrotor seen from above (x-y) with the columns,
    start (blue dot) and goal (red star) of each instance. TO alone and refined come from the refine
    artifact's ``inst_base_X`` / ``inst_pol_X``.
    """
    from sdp_cli.report.figures.plot_dataset import _draw_columns_top, goal_point, trajectory_points

    d = df[df.task == task_name]
    families = {split_family(m)[1] for m in d.method}
    if len(families) > 1:
        raise ValueError(f"trajectories of {task_name}: rows of several TO families {sorted(map(str, families))}; "
                         "draw each of traj_parts")
    family = families.pop() if families else None
    d = _last_iterations(loop_t_a(d))
    found = {m: _best_rollout(g) for m, g in d.groupby("method")}
    found = {m: v for m, v in found.items() if v is not None and "inst_pol_X" in load_npz(v[1], kind="dataset")[0]}
    if not found:
        return []
    runs = {}
    for m, (ro, rf, run) in sorted(found.items(), key=lambda x: method_order(x[0])):
        r, rmeta = load_npz(ro, kind="rollout")
        f, _ = load_npz(rf, kind="dataset")
        runs[split_family(m)[0]] = (r, f, rmeta, run)
    r0, f0, meta0, _ = next(iter(runs.values()))
    task = get_task(task_name, **(meta0.get("task_options") or {}))
    top = task.report_view == "top"
    ix, iy = (0, 1) if top else (1, 2)
    plt = pyplot()
    n_show = min(n_show, len(r0["X"]))
    base_ok = np.asarray(f0["inst_base_converged"], bool) if "inst_base_converged" in f0 else None
    n_lines = len(runs) + 2                      # each panel's title: instance, TO alone, one line per method
    n_leg = -(-(2 * len(runs) + 3) // 6)         # legend rows (6 columns)
    height = 3.0 + 2 * 0.16 * n_lines + 0.22 * n_leg
    fig, axes = plt.subplots(1, n_show, figsize=(3.3 * max(n_show, 2), height), squeeze=False)
    for j, ax in enumerate(axes[0]):
        xi = r0["xi"][j]
        if top:
            _draw_columns_top(ax, task)

        def draw(X, label, **kw):
            if not np.all(np.isfinite(X)):
                return
            if top:
                P = trajectory_points(task, X)
                ax.plot(P[:, ix], P[:, iy], label=label, **kw)
            else:   # pendulums: distance of the tip to the goal over time
                ax.plot(np.arange(len(X)) * task.dt, [task.goal_distance(x, xi) for x in X], label=label, **kw)
        # TO alone that did not converge is drawn dotted: its last iterate, not a solution
        failed = base_ok is not None and not base_ok[j]
        # TO alone first and widest, then each method's policy line (and its refined one) thinner than the last
        lw_to, *lw_pols = line_widths(len(runs) + 1, 1.4, 0.6)
        draw(f0["inst_base_X"][j], "TO alone (naive guess)", color="0.55", lw=lw_to, alpha=0.7, ls=":" if failed else "-")
        for (m, (r, f, _, _)), lw_pol, lw_ref in zip(runs.items(), lw_pols, line_widths(len(runs), 1.0, 0.45)):
            draw(r["X"][j], f"{method_label(m)} policy", color=COLORS.get(m, "tab:orange", among=runs), lw=lw_pol)
            draw(f["inst_pol_X"][j], f"refined from {method_label(m)}", color=COLORS.get(m, "tab:orange", among=runs),
                 lw=lw_ref, ls="--")
        if top:
            P0 = trajectory_points(task, task.initial_state(xi)[None])
            ax.plot(P0[0, ix], P0[0, iy], "o", color="tab:blue", ms=5, label="start")
            g = goal_point(task, xi)
            if g is not None:
                ax.plot(g[ix], g[iy], "*", color="tab:red", ms=10, label="goal")
        else:
            ax.axhline(task.goal_tolerance, color="tab:red", lw=0.8, ls=":", label="goal tolerance")
        to_line = [] if base_ok is None else [f"TO alone: {'not converged (dotted)' if failed else 'converged'}"]
        ax.set_title("\n".join([f"test instance {j}"] + to_line + [
            f"{method_label(m)}: {_outcome(task, r, j)}" + _refine_note(f, j) for m, (r, f, *_) in runs.items()]),
            fontsize=8)
        ax.set_xlabel("x (m)" if top else "time (s)")
        ax.set_ylabel("y (m)" if top else "tip distance to the goal (m)")
        if top:
            ax.set_aspect("equal", adjustable="datalim")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=8, frameon=False)
    what = "the tip's distance to the goal over time" if not top else "seen from above, x-y plane"
    n = len(r0["X"])
    drawn = "instance 0" if n_show == 1 else f"instances 0-{n_show - 1}"
    conv = "" if base_ok is None else f"; TO alone converged on {int(base_ok.sum())} of {n}"
    by = "" if family is None else f" (TO {TO_FAMILIES.get(family, family)})"
    fig.suptitle("\n".join([f"{task_name}{by}: TO alone vs policy vs refined ({what}); {drawn} of {n} drawn (the first, "
                            f"not chosen){conv}"] + [f"{method_label(m)} (its best run by success, {run}): over all {n}, {_shares(r, rmeta)}"
                                               for m, (r, _, rmeta, run) in runs.items()]), fontsize=9)
    fig.tight_layout(rect=(0, (0.22 * n_leg + 0.1) / height, 1, 1))
    return [save_fig(fig, out / (name or f"traj_{task_name}.png"))]

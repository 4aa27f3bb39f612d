"""``ablation_k_<task>``: mean policy cost and success against the number of diffusion steps K.

Drawn when a task has runs of one method at several K (``k_rollout``, the K of training and
rollout), e.g. ``pipelines/ablation_k.yaml`` (the paper's claim that K = 5 suffices, Sec. IV-A):
one line per method and epoch count, mean and 95% interval over seeds, the TO-alone cost as a
reference. Rows are each run's first iteration at its loop T_a.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from sdp_cli.report.figures.paper import _agg
from sdp_cli.report.rows import loop_t_a, mean_ci, method_label
from sdp_cli.report.figures.style import COLORS, pyplot, save_csv, save_fig


def ablation_k(df: pd.DataFrame, task: str, out: Path, carried=None) -> list[Path]:
    d = df[(df.task == task) & (df.iteration == 0)]
    if d.empty or "k_rollout" not in d or d.groupby("method").k_rollout.nunique().max() < 2:
        return []
    d = loop_t_a(d)
    tab = pd.concat([_agg(d, ["method", "epochs", "k_rollout"], col).assign(quantity=name)
                     for col, name in (("policy_cost_mean", "policy cost"), ("success_rate", "success rate"))])
    to = mean_ci(d["to_alone_cost_mean"])[0] if "to_alone_cost_mean" in d else float("nan")
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, quantity in zip(axes, ("policy cost", "success rate")):
        t = tab[tab.quantity == quantity]
        for (method, epochs), g in t.groupby(["method", "epochs"]):
            g = g.sort_values("k_rollout")
            final = epochs == t[t.method == method].epochs.max()
            # the earlier checkpoint: dashed, square markers, drawn a little to the left (no overlap)
            ax.errorbar(g.k_rollout * (1.0 if final else 0.95), g["mean"], yerr=g.ci95.fillna(0),
                        ls="-" if final else "--", marker="o" if final else "s", capsize=3,
                        color=COLORS.get(method), label=f"{method_label(method)} ({int(epochs)} ep.)")
        if quantity == "policy cost" and to == to:
            ax.axhline(to, color="black", ls=":", label="TO alone")
        ax.set_xscale("log")
        ks = sorted(int(k) for k in t.k_rollout.unique())
        ax.set_xticks(ks)
        ax.set_xticklabels([str(k) for k in ks])
        ax.minorticks_off()
        ax.set_xlabel("K (diffusion steps, training and rollout)")
        ax.set_ylabel("mean cost on test instances" if quantity == "policy cost" else "share of rollouts reaching the goal")
        ax.legend(fontsize=8)
    axes[1].set_ylim(-0.03, 1.03)
    n = int(d.groupby(["method", "k_rollout", "epochs"]).train_seed.nunique().min())
    fig.suptitle(f"K ablation, {task} (n_traj {','.join(str(int(v)) for v in sorted(d.n_traj.unique()))}, "
                 f"{n} seeds; mean and 95% interval)", fontsize=10)
    fig.tight_layout()
    return [save_csv(tab, out / f"ablation_k_{task}.csv"), save_fig(fig, out / f"ablation_k_{task}.png")]

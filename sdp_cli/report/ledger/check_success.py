"""The checks that judge how well a policy does: ``reaches`` (the first dataset size from which its cost stays
near TO alone's) and ``solves`` (its success rate, with comparisons to another method and between columns).
Registered by name in :data:`sdp_cli.report.ledger.checks.CHECKS`."""

from __future__ import annotations

from dataclasses import dataclass, field

import pandas as pd

from sdp_cli.report.ledger.base import Check, Outcome, Part
from sdp_cli.report.ledger.kinds import FirstN
from sdp_cli.report.ledger.select import (Selection, column_text, group_label, groups, has, head,
                                          missing_text, show, value_text)
from sdp_cli.report.ledger.verdicts import fmt, pct_text, ratio_verdict
from sdp_cli.report.rows import conversion_text, method_label, per_seed


@dataclass(frozen=True, kw_only=True)
class Reaches(Check):
    """``method``'s first n_traj within ``within`` of TO alone (:class:`FirstN`), per task in ``tasks``; with
    ``against``: that method's first n_traj over ``method``'s against ``ratio`` (a lower bound, ``against``'s largest
    dataset, where it never gets within; a bound under ``lower_bound_min`` is *partly* at best)."""
    kind = "reaches"
    method: str
    tasks: list
    at: str = "final_epochs"
    within: float | None = None
    against: str | None = None
    ratio: float | None = None
    lower_bound_min: float = 0.0
    keep: float | None = None
    partly: float | None = None
    cost: str = "policy_cost_mean"
    reference: str = "to_alone_cost_mean"

    def judge(self, res, ctx) -> Outcome:
        rows = self.selection.rows(res, None)
        methods = [self.method] + ([self.against] if self.against else [])
        out, w = Outcome(), self.within
        for task, g in rows.groupby("task"):
            to = g[self.reference].mean()
            reach = {m: FirstN(g[g.method == m].groupby("n_traj")[self.cost].mean().sort_index(), to, w)
                     for m in methods if (g.method == m).any()}
            if len(reach) < len(methods):
                continue
            where, r = task + conversion_text(g[g.method.isin(methods)]), reach[self.method]
            me = method_label(self.method)
            if not self.against:
                out.parts.append(Part(f"{where}: TO alone {to:.3g}, {me} within {pct_text(w)} {r.text()}",
                                      self.verdict(r.holds)))
            elif not r.holds:
                out.parts.append(Part(f"{where}: {me} never within {pct_text(w)} of TO alone {r.never_text()}",
                                      "not reproduced"))
            else:
                o = reach[self.against]
                n = o.n if o.holds else g[g.method == self.against].n_traj.max()
                bound = "" if o.holds else "> "
                v = (ratio_verdict(n / r.n, self.ratio, self.keep, self.partly)
                     if not bound or n / r.n >= self.lower_bound_min else "partly")
                out.parts.append(Part(f"{where}: {me} {r.text()}, {method_label(self.against)} {o.text()} "
                                      f"({bound}{n / r.n:.2g}x)", v))
        report = self.selection.report(res)
        lack = {t: [method_label(m) for m in methods if not ((report.task == t) & (report.method == m)).any()]
                for t in self.tasks} if report is not None else {}
        if any(lack.values()):
            out.incomplete = True
            out.notes.append(f"{self.experiment} not run on " + ", ".join(f"{t} ({', '.join(ms)})" for t, ms in lack.items() if ms))
        return out

    def rule(self) -> str:
        me = method_label(self.method)
        r = (f"{me} from n_traj n: the smallest dataset from which its mean cost over seeds stays within "
             f"{pct_text(self.within)} of TO alone (at it and every larger one)")
        if self.against:
            r += (f"; {method_label(self.against)}'s n over {me}'s against the paper's {self.ratio:g}x (never: a lower "
                  f"bound, its largest dataset; a bound under {self.lower_bound_min:g}x is partly at best)")
        return r


@dataclass(frozen=True, kw_only=True)
class Solves(Check):
    """``method`` solves (its success rate over seeds >= ``solved``; with ``solves: false``, it does not), per group;
    and, where given, beats ``beats``'s success, is no worse than it on the ``no_worse`` columns (except on the tasks
    in ``exempt``), and has each ``less`` pair ``[a, b]`` with mean a < mean b (``at_most``: <=). ``best_over``: the
    best success over that column's values; ``window: {column: [lo, hi]}``: solves at some values, all within
    [lo, hi]. ``show``: columns shown; ``beside``: other methods shown per group."""
    kind = "solves"
    method: str
    solved: float | None = None
    solves: bool = True
    best_over: str | None = None
    window: dict | None = None
    beats: str | None = None
    no_worse: list = field(default_factory=list)
    exempt: list = field(default_factory=list)
    less: list = field(default_factory=list)
    at_most: list = field(default_factory=list)
    beside: list = field(default_factory=list)
    show: list = field(default_factory=lambda: ["policy_cost_mean", "goal_distance_median"])

    def _numbers(self, g: pd.DataFrame) -> list[str]:
        return [f"success {fmt(per_seed(g, 'success_rate'), pct=True)}"] + show(g, self.show)

    def judge(self, res, ctx) -> Outcome:
        every = self.selection.rows(res, None)
        others = list(dict.fromkeys(([self.beats] if self.beats else []) + self.beside))
        by = {m: groups(every[every.method == m], self.per) if len(every) else {} for m in [self.method] + others}
        keys = list(dict.fromkeys([*by[self.method], *(k for m in others for k in by[m])]))
        out, expect = Outcome(), self.expected()
        report = self.selection.report(res)
        for key in keys:
            g = by[self.method].get(key)
            theirs = {m: by[m][key] for m in others if key in by[m]}
            label = group_label(key, self.per, g if g is not None else next(iter(theirs.values())), every)
            beside = "".join(f"; {method_label(m)}: {', '.join(self._numbers(t))}" for m, t in theirs.items())
            lead = head(label, self.name)
            if g is None:
                begun = report is not None and self._begun(report, key)
                out.parts.append(Part(f"{lead} {'not finished' if begun else 'not run yet'}{beside}", "not run"))
                out.incomplete |= key in expect
                continue
            if self.best_over:
                s = g.groupby(self.best_over).success_rate.mean()
                out.parts.append(Part(f"{lead}: best success over {self.best_over} {100 * s.max():.0f}% "
                                      f"({self.best_over} {s.idxmax():g})", self.verdict((s.max() >= self.solved) == self.solves)))
                continue
            if self.window:
                (col, (lo, hi)), = self.window.items()
                s = g.groupby(col).success_rate.mean()
                at = sorted(float(n) for n in s[s >= self.solved].index)
                out.parts.append(Part(f"{lead} solves at {col} " + (", ".join(f"{n:g}" for n in at) or "none"),
                                      self.verdict(bool(at) and lo <= min(at) and max(at) <= hi)))
                continue
            if self.beats and self.beats not in theirs:
                out.parts.append(Part(f"{lead}: {', '.join(self._numbers(g))}; {method_label(self.beats)} "
                                      f"{'not finished' if report is not None and self._begun(report, key, self.beats) else 'not run yet'}",
                                      "not run"))
                out.incomplete |= key in expect
                continue
            holds, words = self._holds(g, theirs, key)
            out.parts.append(Part(f"{lead}: {', '.join(self._numbers(g) + words)}{beside}", self.verdict(holds)))
        if not keys and not self.per and report is not None:     # one group, not run: the claim waits for it
            begun = len(Selection(self.experiment, self.method, self.where, "rows").rows(res)) > 0
            out.parts.append(Part(f"{self.name}: {'not finished' if begun else 'not run yet'}", "not run"))
            out.incomplete = True
        out.incomplete |= any(k not in by[self.method] for k in expect)
        gone = [k for k in expect if k not in keys]
        if gone:
            out.notes.append(missing_text(self, res, gone, [self.method] + others))
        return out

    def _holds(self, g, theirs, key) -> tuple[bool, list[str]]:
        s = per_seed(g, "success_rate").mean()
        holds, words = (s >= self.solved) == self.solves, []
        for (a, b), strict in [(p, True) for p in self.less] + [(p, False) for p in self.at_most]:
            va, vb = g[a].mean(), g[b].mean()
            holds &= bool(va < vb) if strict else bool(va <= vb)
            words.append(f"{column_text(a)[0]} {value_text(a, va)} vs {column_text(b)[0]} {value_text(b, vb)}")
        if self.beats:
            t = theirs[self.beats]
            holds &= s > per_seed(t, "success_rate").mean()
            task = dict(zip(self.per, key)).get("task")
            for col in self.no_worse:
                if task not in self.exempt and has(g, col):
                    holds &= bool(per_seed(g, col).mean() <= per_seed(t, col).mean())
        return bool(holds), words

    def _begun(self, report: pd.DataFrame, key: tuple, method: str | None = None) -> bool:
        """Whether ``method`` (the judged one) has rows of group ``key`` in the report, at any iteration."""
        d = report[report.method == (method or self.method)] if "method" in report else report
        return bool(len(groups(d, self.per).get(key, ())))

    def rule(self) -> str:
        if self.best_over or self.window:
            return ""
        r = (f"{method_label(self.method)} solves (>= {pct_text(self.solved)} success)" if self.solves else
             f"{method_label(self.method)} does not solve (< {pct_text(self.solved)} success)")
        r += "".join(f", {column_text(a)[0]} < {column_text(b)[0]}" for a, b in self.less)
        r += "".join(f", {column_text(a)[0]} <= {column_text(b)[0]}" for a, b in self.at_most)
        if self.beats:
            r += f", beats {method_label(self.beats)}'s success"
            r += "".join(f" and has no more {column_text(c)[0]}" for c in self.no_worse)
            r += f" (except on {', '.join(self.exempt)})" if self.exempt and self.no_worse else ""
        return r

"""The checks that judge a number against the paper's: ``ratio`` (within one evaluation, per seed),
``degradation``, ``share``, ``within``, ``near`` (a bench's value), and ``show`` (shown, never judged).
Registered by name in :data:`sdp_cli.report.ledger.checks.CHECKS`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from sdp_cli.report.ledger.base import SHOWN, Check, Outcome, Part
from sdp_cli.report.ledger.kinds import Ratio, Within
from sdp_cli.report.ledger.select import (BASELINES, SHORT, Selection, baselines, column_text, group_label, groups, has, head,
                                          join_words, paper_ratio, show)
from sdp_cli.report.ledger.verdicts import all_any, fmt, pct_text, ratio_verdict
from sdp_cli.report.rows import method_label, per_seed


@dataclass(frozen=True, kw_only=True)
class RatioCheck(Check):
    """``num / den`` within each row (one evaluation), per seed, then the mean, against the paper's ratio ``paper``
    (a number or ``[a, b]``), per group and TO baseline (:class:`Ratio`); ``show``: the columns beside it."""
    kind = "ratio"
    method: str
    num: str
    den: str
    paper: float | list
    keep: float | None = None
    partly: float | None = None
    baselines: list = field(default_factory=list)
    show: list = field(default_factory=list)

    def validate(self) -> None:
        baselines(self.baselines, {})

    def judge(self, res, ctx) -> Outcome:
        rows, out = self.selection.rows(res), Outcome()
        report = self.selection.report(res)
        if rows.empty:
            if report is not None:
                begun = len(Selection(self.experiment, self.method, self.where, "rows").rows(res)) > 0
                out.parts.append(Part(f"{', '.join(x for x in (self.label.rstrip(','), self.name) if x)}: "
                                      f"{'partway (no run at its final iteration yet)' if begun else 'not run yet'}", "not run"))
            return out
        for pre, name in baselines(self.baselines, ctx):
            num, den = self.num.format(to=pre), self.den.format(to=pre)
            if not (has(rows, num) and has(rows, den)):
                continue
            for key, g in groups(rows, self.per).items():
                r = Ratio.of(g, num, den, paper_ratio(self.paper), self.keep, self.partly,
                             join_words(self.label, group_label(key, self.per, g, rows), name))
                beside = show(g, [c.format(to=pre) for c in self.show])
                out.parts.append(Part(r.text() + (f" ({', '.join(beside)})" if beside else ""),
                                      r.verdict if self.judged else SHOWN))
        return out

    def rule(self) -> str:
        if not self.judged:
            return ""
        r = Ratio(pd.Series(dtype=float), paper_ratio(self.paper), self.keep, self.partly)
        label = "" if self.label == self.experiment else self.label.rstrip(",")
        return (f"{label or 'the ratio'}: {column_text(self.num.format(to=''))[0]} / "
                f"{column_text(self.den.format(to=''))[0]} within one evaluation, per seed, against the paper's "
                f"{paper_ratio(self.paper):.3g}x (reproduced from {r.lines()['reproduced']:.3g}x, partly from "
                f"{r.lines()['partly']:.3g}x)")


@dataclass(frozen=True, kw_only=True)
class Degradation(Check):
    """The worst mean ``column`` at ``over`` >= ``high_from`` over the worst at ``over`` <= ``low_to`` (the paper's
    ``[a, b]``), judged as a ratio; *not run* with fewer than ``min_values`` values of ``over``."""
    kind = "degradation"
    method: str
    paper: list
    high_from: float
    low_to: float
    at: str = "sweep"
    column: str = "policy_cost_mean"
    over: str = "t_a"
    min_values: int = 3
    keep: float | None = None
    partly: float | None = None

    def judge(self, res, ctx) -> Outcome:
        rows, out = self.selection.rows(res), Outcome()
        if self.selection.report(res) is None:
            return out
        o = SHORT.get(self.over, self.over)
        if rows.empty or rows[self.over].nunique() < self.min_values:
            out.parts.append(Part(f"{self.name}: the {o} sweep not run yet", "not run"))
            return out
        by = rows.groupby(self.over)[self.column].mean()
        lo, hi = by[by.index <= self.low_to].max(), by[by.index >= self.high_from]
        r = hi.max() / lo if len(hi) else np.nan
        words = column_text(self.column)[0]
        out.parts.append(Part(f"{self.name} {words} at {o} >= {self.high_from:g}: " + ", ".join(f"{c:.3g}" for c in hi)
                              + f" vs worst {lo:.3g} at {o} <= {self.low_to:g} ({r:.2f}x)",
                              ratio_verdict(r, paper_ratio(self.paper), self.keep, self.partly) if self.judged else SHOWN))
        return out

    def rule(self) -> str:
        o = SHORT.get(self.over, self.over)
        return (f"degradation: the worst mean {column_text(self.column)[0]} at {o} >= {self.high_from:g} over the worst "
                f"at {o} <= {self.low_to:g}, against the paper's {paper_ratio(self.paper):.3g}x")


@dataclass(frozen=True, kw_only=True)
class Share(Check):
    """Per group, each method's share: of its rows with ``column`` > ``above``, or ``1 -`` the mean of ``column``
    (``complement``), or the mean of ``column``; holds where every one of ``methods`` has run, its share is at least
    ``line`` and more than each of ``than``'s. A group where only some of ``methods`` ran is named, not judged."""
    kind = "share"
    methods: list
    column: str
    line: float
    at: str = "rows"
    above: float | None = None
    complement: bool = False
    than: list = field(default_factory=list)
    baselines: list = field(default_factory=list)
    show: list = field(default_factory=list)

    def validate(self) -> None:
        baselines(self.baselines, {})

    def _share(self, g: pd.DataFrame, col: str) -> float:
        if self.above is not None:
            return float((g[col] > self.above).mean())
        return float(1 - g[col].mean()) if self.complement else float(g[col].mean())

    def judge(self, res, ctx) -> Outcome:
        rows, out = self.selection.rows(res, None), Outcome()
        mine = rows[rows.method.isin(self.methods + self.than)] if len(rows) else rows
        for pre, name in baselines(self.baselines, ctx):
            col = self.column.format(to=pre)
            if not has(mine, col):
                continue
            for key, g in groups(mine, self.per).items():
                share = {m: self._share(gm, col) for m, gm in sorted(g.groupby("method"))}
                if not any(m in share for m in self.methods):     # none of the judged methods here: nothing to say
                    continue
                label = ", ".join(x for x in (join_words(self.label, f"({name})" if name else ""),
                                              group_label(key, self.per, g[g.method.isin(self.methods)], mine)) if x)
                pct = ", ".join(f"{method_label(m)} {100 * v:.0f}%" for m, v in share.items()) if len(
                    self.methods + self.than) > 1 else f"{100 * next(iter(share.values())):.0f}%"
                beside = show(g[g.method.isin(self.methods)], [c.format(to=pre) for c in self.show])
                text = f"{label}: {pct}" + (f" ({', '.join(beside)})" if beside else "")
                lack = [method_label(m) for m in self.methods if m not in share]
                if lack:
                    out.parts.append(Part(f"{text} (not judged: {', '.join(lack)} not run)", "not run"))
                    out.incomplete = True
                    continue
                low = min(share[m] for m in self.methods)
                holds = low >= self.line and all(low > share[t] for t in self.than if t in share)
                out.parts.append(Part(text, self.verdict(holds)))
        if not out.parts and self.selection.report(res) is not None:
            out.parts.append(Part(f"{join_words(self.label, ', '.join(map(method_label, self.methods)))}: not run yet", "not run"))
        return out

    def rule(self) -> str:
        what = self.label or (f"the share of rows with {self.column} > {self.above:g}" if self.above is not None
                              else column_text(self.column.format(to=""))[0])
        if len(self.methods) == 1 and not self.than:
            return f"{what} >= {pct_text(self.line)} ({method_label(self.methods[0])}'s evaluations)"
        than = f", more than {', '.join(map(method_label, self.than))}'s" if self.than else ""
        return f"{what} >= {pct_text(self.line)} for each of {', '.join(map(method_label, self.methods))}{than}"


@dataclass(frozen=True, kw_only=True)
class WithinCheck(Check):
    """The mean over seeds of ``value`` within ``within`` of ``reference``'s (:class:`Within`); each a mapping
    ``{column, method, where, at, label}`` of rows of the check's report (unset keys: the check's)."""
    kind = "within"
    value: dict
    reference: dict
    within: float | None = None

    def _side(self, res, side: dict) -> tuple[pd.Series, str]:
        sel = Selection(self.experiment, side.get("method", self.method), side.get("where", {}), side.get("at", self.at))
        rows = sel.rows(res)
        return (per_seed(rows, side["column"]) if len(rows) else pd.Series(dtype=float)), side.get("label", side["column"])

    def judge(self, res, ctx) -> Outcome:
        out = Outcome()
        if self.selection.report(res) is None:
            return out
        (v, vl), (r, rl) = self._side(res, self.value), self._side(res, self.reference)
        if v.empty or r.empty:
            out.parts.append(Part(f"{vl if v.empty else rl}: not run yet", "not run"))
            return out
        w = Within(v.mean(), r.mean(), self.within)
        out.parts.append(Part(f"{vl} {fmt(v)} vs {rl} {fmt(r)} ({w.text()})", self.verdict(w.holds)))
        return out

    def rule(self) -> str:
        return f"{self.value.get('label', 'the value')} within {pct_text(self.within)} of {self.reference.get('label', 'the reference')}"


@dataclass(frozen=True, kw_only=True)
class Near(Check):
    """Each of a bench's rows: ``column`` within ``tolerance`` of the paper's ``paper``; ``describe``: the columns
    that name a row (the first one as it is, the others by name)."""
    kind = "near"
    column: str
    paper: float
    tolerance: float
    at: str = "rows"
    describe: list = field(default_factory=list)

    def judge(self, res, ctx) -> Outcome:
        rows, out = self.selection.rows(res, None), Outcome()
        if self.selection.report(res) is None:
            return out
        if rows.empty:
            out.parts.append(Part(f"{self.label}: no row of {self.experiment} selected", "not run"))
            return out
        ok = [abs(v - self.paper) <= self.tolerance for v in rows[self.column]]
        desc = lambda r: ", ".join(str(r[c]) if i == 0 else f"{c} {r[c]}" for i, c in enumerate(self.describe))  # noqa: E731
        text = "; ".join(f"{r[self.column]:.2f} ({desc(r)})" for _, r in rows.iterrows())
        out.parts.append(Part(f"{self.label}: {text}", all_any(ok) if self.judged else SHOWN))
        return out

    def rule(self) -> str:
        return f"{self.label or self.column} within {self.tolerance:g} of the paper's {self.paper:g}, per row"


@dataclass(frozen=True, kw_only=True)
class Show(Check):
    """``columns`` of the selected rows per group (mean over seeds with its interval), shown, never judged."""
    kind = "show"
    columns: list
    judged: bool = False

    def judge(self, res, ctx) -> Outcome:
        rows, out = self.selection.rows(res), Outcome()
        for key, g in groups(rows, self.per).items():
            lead = join_words(head(group_label(key, self.per, g, rows), self.name), self.label)
            cols = [c.format(to=p) for p, _ in baselines(list(BASELINES), ctx) for c in self.columns] if any(
                "{to}" in c for c in self.columns) else self.columns
            out.parts.append(Part(f"{lead}: {', '.join(show(g, list(dict.fromkeys(cols))))}", SHOWN))
        return out

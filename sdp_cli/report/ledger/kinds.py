"""The typed results a check judges with (:mod:`sdp_cli.report.ledger.checks`), each saying its verdict and
writing its own prose; the lines they are judged against come from results/claims.yaml (a check's fields over
the shared ``rules``).

- :class:`Ratio`: per-seed ratios, each taken within one evaluation (never across evaluations made under
  other load), against the paper's ratio: *reproduced* when the mean keeps ``keep`` of the paper's effect
  (``r - 1 >= keep (r_paper - 1)``), *partly* with ``partly`` of it; a mean whose 95% interval straddles one
  of those two lines says so.
- :class:`Within`: a mean cost within a share of a reference (TO alone's cost, another K's).
- :class:`FirstN`: the smallest dataset from which a mean cost stays within a share of a reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from sdp_cli.report.ledger.verdicts import fmt, pct_text, ratio_verdict
from sdp_cli.report.rows import mean_ci, per_seed


@dataclass(frozen=True)
class Ratio:
    """A ratio claim. ``per_seed``: ours, one value per training seed (each the mean of that seed's ratios
    taken within one evaluation); ``paper``: the paper's ratio (> 1); ``label``: what the ratio is, written
    before the number."""
    per_seed: pd.Series
    paper: float
    keep: float
    partly: float
    label: str = ""

    @classmethod
    def of(cls, rows: pd.DataFrame, num: str, den: str, paper: float, keep: float, partly: float,
           label: str = "") -> "Ratio":
        """``rows[num] / rows[den]`` within each row (one evaluation), averaged per training seed."""
        return cls(per_seed(rows.assign(_ratio=rows[num] / rows[den]), "_ratio"), paper, keep, partly, label)

    @property
    def mean(self) -> float:
        return mean_ci(self.per_seed)[0]

    @property
    def verdict(self) -> str:
        return ratio_verdict(self.mean, self.paper, self.keep, self.partly)

    def lines(self) -> dict[str, float]:
        """The ratios from which ours is *reproduced* and *partly*."""
        return {"reproduced": 1 + self.keep * (self.paper - 1), "partly": 1 + self.partly * (self.paper - 1)}

    def straddled(self) -> list[str]:
        """The verdict lines that the 95% interval of the mean over seeds holds (``[]``: none, or no interval)."""
        m, h, _ = mean_ci(self.per_seed)
        if not (np.isfinite(m) and np.isfinite(h)):
            return []
        return [name for name, line in self.lines().items() if m - h < line < m + h]

    def text(self) -> str:
        """``"label: 2.75x ± 0.283x (3 seeds; its interval straddles the verdict line: partly from 2.76x)"``."""
        value = fmt(self.per_seed, unit="x")
        s = self.straddled()
        if s:
            lines = ", ".join(f"{name} from {self.lines()[name]:.3g}x" for name in s)
            value = value[:-1] + f"; its interval straddles the verdict line: {lines})"
        return f"{self.label}: {value}" if self.label else value


@dataclass(frozen=True)
class Within:
    """``value`` within ``share`` of ``reference`` (a mean cost against TO alone's or another setting's)."""
    value: float
    reference: float
    share: float

    @property
    def holds(self) -> bool:
        return bool(self.value <= (1 + self.share) * self.reference)

    def text(self) -> str:
        return f"{'within' if self.holds else 'not within'} {pct_text(self.share)}"


@dataclass(frozen=True)
class FirstN:
    """The smallest dataset from which a method "reaches" a cost: ``by``, the mean cost over seeds per n_traj
    (by increasing n_traj); ``to``: the cost to reach (TO alone's); ``within``: the share allowed above it.
    "Needs n trajectories" means n and more suffice: a small dataset within by chance while larger ones are not
    does not count (:attr:`first` is the first within, printed beside it where it differs)."""
    by: pd.Series
    to: float
    within: float

    @property
    def n(self) -> float:
        """Smallest n_traj within at it and at every larger n_traj run (inf: none)."""
        ok = (self.by <= (1 + self.within) * self.to)[::-1].cummin()[::-1]
        return float(ok[ok].index.min()) if ok.any() else float("inf")

    @property
    def first(self) -> float:
        """Smallest n_traj within (inf: none)."""
        ok = self.by[self.by <= (1 + self.within) * self.to]
        return float(ok.index.min()) if len(ok) else float("inf")

    @property
    def holds(self) -> bool:
        return bool(np.isfinite(self.n))

    def text(self) -> str:
        """``"from n_traj N"`` (with the first n_traj within where it differs) or ``"never (...)"``."""
        n, first = self.n, self.first
        if not np.isfinite(n):
            return "never " + self.never_text()
        return f"from n_traj {n:g}" + (f" (first within at n_traj {first:g})" if first != n and np.isfinite(first) else "")

    def never_text(self) -> str:
        """``"(over n_traj 2-4; lowest mean cost 15.3 at n_traj 4)"``: what "never" was judged on (a sweep still
        running has fewer dataset sizes) and how close it came, naming a first n_traj within that a larger one
        left again."""
        by, first = self.by, self.first
        span = f"{by.index[0]:g}-{by.index[-1]:g}" if len(by) > 1 else f"{by.index[0]:g}"
        again = f"; first within at n_traj {first:g}, left again at a larger one" if np.isfinite(first) else ""
        return f"(over n_traj {span}; lowest mean cost {by.min():.3g} at n_traj {by.idxmin():g}{again})"

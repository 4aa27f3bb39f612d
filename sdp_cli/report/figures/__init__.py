"""The report's figures and tables (``sdp report``): one registry, :data:`FIGURES`.

A figure is a function ``draw(rows, task, out, carried) -> [written paths]`` that writes
``<name>_<task>.{csv,md,png}`` into ``out`` (or files under ``out/<name>/``) from the evaluation rows it is
given: ``"raw"`` rows (all_runs.csv as read), ``"variants"`` (a method's variants apart, every budget:
:func:`~sdp_cli.report.rows.method_variants`) or ``"budget"`` (one budget per method:
:func:`~sdp_cli.report.rows.largest_budget`); ``carried`` is the earlier report's part kept by
``--keep-missing`` (:class:`~sdp_cli.report.carry.Carried`) for figures drawn from a run's files. Adding a
figure is its module plus one line here; :mod:`sdp_cli.report.make` draws every registered figure for every
task, in this order, and removes stale files by these names.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable

from sdp_cli.report.figures.ablation import ablation_k
from sdp_cli.report.figures.curves import loop_costs
from sdp_cli.report.figures.paper import fig1, fig2a, fig2b, table2c
from sdp_cli.report.figures.timing import timing
from sdp_cli.report.figures.traj import traj


@dataclass(frozen=True)
class Figure:
    name: str
    draw: Callable
    rows: str = "budget"          # "raw", "variants" or "budget" (see the module docstring)
    folder: bool = False          # writes under out/<name>/ rather than <name>_<task>.* files


FIGURES = (
    Figure("ablation_k", ablation_k, rows="raw"),          # the K ablation (Sec. IV-A)
    Figure("fig1", fig1, rows="variants"),                 # cost vs n_traj, every budget
    Figure("timing", timing, rows="variants"),             # where the time goes
    Figure("fig2a", fig2a),                                # cost per loop iteration
    Figure("fig2b", fig2b),                                # TO iterations, warm vs naive
    Figure("table2c", table2c),                            # the T_a trade-off
    Figure("traj", traj),                                  # trajectories of a few test instances
    Figure("loop", loop_costs, folder=True),               # dvc plots series per iteration
)

#: the files ``sdp report`` writes into its output folder (hand-written ones such as NOTES.md are kept)
REPORT_FILE = re.compile(r"^(all_runs\.csv|README\.md|(" + "|".join(f.name for f in FIGURES if not f.folder)
                         + r")_.+\.(csv|md|png))$")

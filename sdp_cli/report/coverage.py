"""How much of an experiment a report holds: per group of ``pipelines/<name>.yaml``, its runs that reached
their last iteration, those partway (with ``evaluated / n_algo``) and those not in the report.

A report drawn while runs go on (or after some were left out for lack of time) says so in its README
instead of letting a figure pass for the whole experiment, and a complete one says that it is; finished
runs of an older results version than the code's (:data:`sdp_cli.RESULTS_VERSION`, the rows'
``results_version``) are counted apart, and partway ones name their version: they are still to be
re-made. Reads the experiment file only (:mod:`sdp_cli.experiments.experiment`), never the runs' folders: the rows
given are what the report drew.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from sdp_cli import RESULTS_VERSION
from sdp_cli.experiments.experiment import check_group, group_items, group_run_names, load_experiment

#: partway runs named per group before "and N more"
MAX_NAMED = 6


def experiment_coverage(df: pd.DataFrame, name: str, root: Path = Path("."),
                        hours: dict[str, float] | None = None) -> pd.DataFrame:
    """One row per group of experiment ``name``: ``group`` (task, methods, tag or epochs), ``runs``,
    ``finished`` (every iteration evaluated, the last at the group's epochs), ``partway`` (names with
    ``k/n_algo`` iterations, or the epochs evaluated so far, and the results version of those of an older one),
    ``older``: the finished runs whose rows are of an older results version than the code's, ``older_h`` the
    estimated hours of re-making them, ``older_partway``: the partway runs of an older version, ``not_run``, and
    ``not_run_h``: the estimated hours of the runs not run; hours are summed over those ``hours``
    (``{run: hours}``, a saved ``--estimate``) has (NaN when it has none of them).
    ``df``: the report's rows (``run``, ``iteration``)."""
    spec = load_experiment(name, root)
    reached = (df.groupby("run").iteration.max() + 1).to_dict() if len(df) else {}
    epochs = df.groupby("run").epochs.max().to_dict() if len(df) and "epochs" in df else {}
    version = (df.groupby("run").results_version.min().to_dict()
               if len(df) and "results_version" in df else {})
    rows = []
    for gi, raw in group_items(spec):
        g = check_group(name, gi, raw)
        keys = group_run_names(g)
        n_algo = int(g["n_algo"])
        # finished: the last iteration evaluated at the group's epochs (not only at a `save_at` checkpoint)
        done = [k for k in keys if reached.get(k, 0) >= n_algo and epochs.get(k, g["epochs"]) >= g["epochs"]]
        stale = {k for k in keys if version.get(k, RESULTS_VERSION) < RESULTS_VERSION}
        part = [f"{k} " + (f"{reached[k]}/{n_algo}" if reached[k] < n_algo else f"{epochs[k]:g}/{g['epochs']:g} epochs")
                + (f" of results version {version[k]:g}" if k in stale else "")
                for k in keys if k in reached and k not in done]
        label = f"{g['task']} {', '.join(g['methods'])}" + (f" {g['tag']}" if g["tag"] else f", {g['epochs']:g} epochs")
        named = ", ".join(part[:MAX_NAMED]) + (f" and {len(part) - MAX_NAMED} more" if len(part) > MAX_NAMED else "")
        todo = [k for k in keys if k not in done and k not in reached]
        known = [hours[k] for k in todo if k in (hours or {})]
        older = [k for k in done if k in stale]
        older_known = [hours[k] for k in older if k in (hours or {})]
        older_part = [k for k in keys if k in stale and k in reached and k not in done]
        part_h = [hours[k] for k in older_part if k in (hours or {})]
        named += f"; {sum(part_h):.1f} h to re-make" if part_h else ""
        rows.append({"group": label, "runs": len(keys), "finished": len(done), "older": len(older),
                     "older_partway": len(older_part),
                     "older_h": sum(older_known) if older_known else float("nan"),
                     "partway": f"{len(part)}" + (f" ({named})" if part else ""),
                     "not_run": len(todo), "not_run_h": sum(known) if known else float("nan")})
    return pd.DataFrame(rows)


def coverage_lines(df: pd.DataFrame, name: str, root: Path = Path("."),
                   hours: dict[str, float] | None = None, hours_from: str = "") -> list[str]:
    """The README section of :func:`experiment_coverage`: one line when every run finished at the code's
    results version, else a table per group; with ``hours`` (read from ``hours_from``), the runs not run
    carry their estimated hours. Empty for an experiment of no groups."""
    cov = experiment_coverage(df, name, root, hours)
    if cov.empty:
        return []
    total, fin, old = int(cov.runs.sum()), int(cov.finished.sum()), int(cov.older.sum())
    stale = old + int(cov.older_partway.sum())
    head = f"## Runs of `pipelines/{name}.yaml` in this report:"
    if fin == total and not old:
        return ["", f"{head} all {total} finished, none of an older results version than {RESULTS_VERSION}"]
    lines = ["", f"{head} {fin} of {total} finished"
             + (f", {old} of them of an older results version than {RESULTS_VERSION}" if old else ""), "",
             "Partway: iterations evaluated of the run's n_algo (stopped or still running); not run: no evaluation "
             "yet. Figures and the ledger use what is here." + (
                 f" Older results version: evaluated by code that measured otherwise than version {RESULTS_VERSION} "
                 "(the revision table below), to be re-made." if stale else "") + (
                 f" Hours of the runs not run (and to re-make): `sdp pipeline {name} --estimate` as saved in "
                 f"`{hours_from}` (every stage, one process on the CPU)." if hours else ""), "",
             "| group | runs | finished | partway | not run |", "|---|---|---|---|---|"]

    def todo(r) -> str:
        return f"{r.not_run}" + (f" ({r.not_run_h:.1f} h)" if r.not_run and pd.notna(r.not_run_h) else "")

    def fin_cell(r) -> str:
        h = f", {r.older_h:.1f} h to re-make" if pd.notna(r.older_h) else ""
        return f"{r.finished}" + (f" ({r.older} of an older results version{h})" if r.older else "")
    lines += [f"| {r.group} | {r.runs} | {fin_cell(r)} | {r.partway} | {todo(r)} |" for r in cov.itertuples()]
    return lines

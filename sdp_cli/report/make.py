"""``sdp report``: the paper's tables and figures from whatever runs exist.

Per task found under ``--runs`` (file names carry the task):

- ``fig1_<task>``: mean policy cost vs n_traj per method and epoch count (iteration 0),
  mean and 95% CI over seeds, TO-alone line, an infinity marker when the mean exceeds 1e5, and
  the policy success rate beside it;
- ``fig2a_<task>``: mean cost per algorithm iteration, policy and refined, per method;
- ``fig2b_<task>``: histogram of TO iterations with (policy warm start) and without (naive);
- ``table2c_<task>``: the T_a trade-off (policy cost, refined cost, TO iterations, rollout,
  solving and total time, TO-alone columns) at the last iteration, CSV and markdown;
- ``traj_<task>``: trajectories of the first test instances, TO alone vs policy vs refined, each
  rollout's outcome (:mod:`sdp_cli.report.figures.traj`);
- ``timing_<task>``: where the time goes (collection, training, evaluation), per iteration;
- variants of a method (K, or (T_h, T_a)) are drawn apart (:func:`method_variants`); all but
  ``fig1`` and ``timing`` show, per method, the runs of the largest budget (:func:`largest_budget`);
- ``all_runs.csv`` (every row) and ``README.md`` (index with commit and budgets, and for an
  experiment of ``pipelines/`` with runs missing, how many it holds: :mod:`sdp_cli.report.coverage`;
  a hand-written ``NOTES.md`` in the output folder, if any, is linked from it).

When the output folder sits in a folder named ``results`` (``results/<experiment>``), the
top index ``results/README.md`` is rewritten too: one line per experiment folder with the
commit that produced it.
"""

from __future__ import annotations

from pathlib import Path
import shutil
import tempfile

import pandas as pd

from sdp_cli.data.artifacts import atomic_write_bytes, code_revision
from sdp_cli.errors import SdpError
from sdp_cli.report.carry import Carried, carried_lines, carry_over, fresh_methods
from sdp_cli.report.coverage import coverage_lines
from sdp_cli.report.estimates import estimated_hours
from sdp_cli.report.rows import largest_budget, loop_t_a, method_variants, newest_version_mask
from sdp_cli.report.runs import PATH_COLUMNS, load_runs, run_revisions
from sdp_cli.report.figures.style import save_csv
from sdp_cli.report.versions import with_results_version
from sdp_cli.data.artifacts import IGNORED_TIMINGS


def current_runs(experiment: str, params: Path = Path("params.yaml")) -> set[str] | None:
    """The runs of ``experiment`` when ``params.yaml`` selects it (the DVC flow), or None (report
    everything: ``sdp loop`` folders, another experiment's runs)."""
    import yaml

    from sdp_cli.experiments.experiment import load_experiment, run_names

    if not params.is_file():
        return None
    spec = yaml.safe_load(params.read_text()) or {}
    if spec.get("experiment") != experiment or not (Path("pipelines") / f"{experiment}.yaml").is_file():
        return None
    return set(run_names(experiment, load_experiment(experiment)))


def make_report(runs: str | Path, out: str | Path, experiment: str | None = None,
                log=lambda s: None, metrics: str | Path | None = None, keep_missing: bool = False) -> list[Path]:
    """Write every table and figure the available runs allow; returns the written paths.
    ``metrics``: also write the last iteration's means per task and method there (JSON, DVC metrics).

    For the experiment that ``params.yaml`` selects, only its current runs are reported: folders of
    runs the experiment file no longer has (e.g. another n_traj sweep), which the persistent DVC
    output keeps, are ignored (and counted in the log).

    ``keep_missing``: extend the report already in ``out`` instead of replacing it: the rows (and per-run
    tables) of runs with no evaluation under ``runs`` are kept from it (:mod:`sdp_cli.report.carry`).

    All or nothing: the files are written into a hidden folder beside ``out`` and moved into ``out`` once every
    one is written, so an error or an interrupt midway leaves the earlier report as it was."""
    runs, out = Path(runs), Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.report-", dir=out.parent))
    IGNORED_TIMINGS.clear()
    try:
        files, df = _write(runs, out, stage, experiment, log, keep_missing)
        written = _publish(stage, out, files)
    finally:
        shutil.rmtree(stage, ignore_errors=True)     # this call's own staging folder, empty once published
    if IGNORED_TIMINGS:   # e.g. after `dvc checkout` restored another run's artifacts beside this machine's timings
        first = sorted(IGNORED_TIMINGS)[0]
        log(f"ignored {len(IGNORED_TIMINGS)} timing file(s) whose artifact changed since they were written "
            f"(e.g. {first}): those times are left out of the report")
    if metrics is not None:
        from sdp_cli.report.figures.curves import metrics_summary, write_metrics

        loop_rows = pd.concat([loop_t_a(df[df.task == t]) for t in sorted(df.task.dropna().unique())])
        write_metrics(metrics_summary(loop_rows), Path(metrics))
    if out.resolve().parent.name == "results":
        written.append(_top_index(out.resolve().parent))
    return written


def _publish(stage: Path, out: Path, written: list[Path]) -> list[Path]:
    """Move the files of ``written`` that lie in ``stage`` to the same place in ``out`` (each an atomic rename;
    the others are earlier report files ``out`` keeps), then move what ``out`` holds of an earlier report and
    this one did not write aside (:func:`_remove_stale`); returns the paths in ``out``."""
    out.mkdir(exist_ok=True)
    final = []
    for p in written:
        if p.resolve().is_relative_to(stage.resolve()):
            dest = out / p.resolve().relative_to(stage.resolve())
            dest.parent.mkdir(parents=True, exist_ok=True)
            p.replace(dest)
            p = dest
        final.append(p)
    _remove_stale(out, final)
    return final


def _write(runs: Path, out: Path, stage: Path, experiment: str | None, log,
           keep_missing: bool) -> tuple[list[Path], pd.DataFrame]:
    """The report's files, written into ``stage`` (the earlier report read from ``out``): their paths (a kept
    earlier file: its path in ``out``) and the rows reported."""
    df = load_runs(runs, log=log, allow_empty=keep_missing)
    kept: frozenset[str] = frozenset()
    if keep_missing:
        df, kept = carry_over(df, out, log)
    current = current_runs(experiment or runs.name)
    if current is not None:
        keep = df.run.isin(current)
        if not keep.all():
            log(f"ignoring {int((~keep).sum())} evaluation(s) in {runs} of runs the current experiment "
                f"{experiment or runs.name!r} no longer has")
        df = df[keep]
        if df.empty:
            raise SdpError(f"no evaluation of the current experiment {experiment or runs.name!r} in {runs}; "
                           f"run `dvc repro` first")
    df = with_results_version(df)
    written = [save_csv(df.drop(columns=[c for c in PATH_COLUMNS if c in df]), stage / "all_runs.csv")]
    from sdp_cli.report.figures import FIGURES
    from sdp_cli.report.figures.curves import training_curves
    from sdp_cli.report.figures.traj import traj_parts

    newest = newest_version_mask(df)   # a task's rows of an older results version beside a newer one's: not drawn
    shown, hidden = df[newest], df.run[~newest].nunique()
    if hidden:
        log(f"not drawn: {hidden} run(s) of an older results version than other runs of their task and TO family")
    fdf = method_variants(shown)
    kept_all, kept = kept, frozenset(kept & set(shown.run))   # (the hidden runs' curves are kept as data)
    bdf = largest_budget(fdf)
    carried = Carried(out, kept, fresh_methods(fdf, kept))
    # one budget per method: a method whose fresh runs are all at another budget still needs its carried rows
    # there (UR5 DP: fresh at n_traj 2-8, drawn at 32 from the earlier report)
    drawn = Carried(out, kept, fresh_methods(bdf, kept))
    rows = {"raw": (shown, None), "variants": (fdf, carried), "budget": (bdf, drawn)}
    kept_traj = [name for t in sorted(bdf.task.dropna().unique()) for name, part in traj_parts(bdf, t)
                 if drawn.kept_traj(part, name)]
    for fig in (f for f in FIGURES if f.rows == "raw"):        # the raw rows' figures first, then per task
        for task in sorted(shown.task.dropna().unique()):
            written += fig.draw(shown, task, stage, None)
    for task in sorted(fdf.task.dropna().unique()):
        for fig in (f for f in FIGURES if f.rows != "raw"):
            d, c = rows[fig.rows]
            written += fig.draw(d, task, stage, c)
    written += training_curves(shown, stage) + [p for r in sorted(kept_all) for p in sorted((out / "curves").glob(f"{r}-it*.csv"))]
    lines = carried_lines(fdf, carried, kept_traj, kept_all - kept)
    written.append(_index(method_variants(df), runs, out, experiment, written, lines,
                          stage, hidden=hidden))
    return written, df


def _remove_stale(out: Path, written: list[Path]) -> list[Path]:
    """Move report files an earlier report left in ``out`` that this one did not write (e.g. a task or a figure
    whose runs are gone, a series renamed) into ``out/.superseded/`` (git-ignored), so the folder shows this
    report only and nothing is deleted; returns their new paths."""
    keep = {p.resolve() for p in written}
    from sdp_cli.report.figures import FIGURES, REPORT_FILE

    stale = [p for p in out.iterdir() if p.is_file() and REPORT_FILE.match(p.name) and p.resolve() not in keep]
    for sub in ["curves"] + [f.name for f in FIGURES if f.folder]:    # the dvc plots series are all the report's
        if (out / sub).is_dir():
            stale += [p for p in (out / sub).iterdir() if p.is_file() and p.resolve() not in keep]
    moved = []
    for p in stale:
        dest = out / ".superseded" / p.relative_to(out)
        dest.parent.mkdir(parents=True, exist_ok=True)
        moved.append(p.replace(dest))
    return moved


def _top_index(results: Path) -> Path:
    """``results/README.md``: each experiment folder's index, with the commit of the code that produced it."""
    lines = ["# Results", "", "One folder per experiment, written by `sdp report` from real runs. Each folder's",
             "README.md names the runs, the commit, and the seeds and budgets of every file in it.", "",
             "The paper's claims beside our numbers: [PAPER.md](PAPER.md) (`sdp report --ledger results/PAPER.md`).", "",
             "| experiment | code commit | files |", "|---|---|---|"]
    for sub in sorted(p for p in results.iterdir() if (p / "README.md").is_file()):
        text = (sub / "README.md").read_text()
        commit = next((ln.split("commit `")[1].split("`")[0] for ln in text.splitlines()
                       if "commit `" in ln), "unknown")
        n_files = sum(1 for f in sub.iterdir() if f.is_file() and f.name != "README.md")
        lines.append(f"| [{sub.name}]({sub.name}/README.md) | `{commit}` | {n_files} |")
    return atomic_write_bytes(results / "README.md", lambda f: f.write(("\n".join(lines) + "\n").encode()))


def _ints(values: pd.Series) -> str:
    """The distinct integers of ``values``, sorted and comma-joined (``"0,1,2"``)."""
    return ",".join(str(int(v)) for v in sorted(set(values.dropna())))


def revision_lines(df: pd.DataFrame) -> list[str]:
    """README section: which code revision made which seeds and iterations, per task and method."""
    revs = run_revisions(df)
    if revs.empty:
        return []
    versions = "results_version" in revs
    lines = ["", "## Code revisions of the runs (from the evaluation manifests)", ""]
    if versions:   # what the runs measure (sdp_cli.RESULTS_VERSION; before version 4: of the revision, versions.py)
        revs = revs.assign(results_version=revs.results_version.map(lambda v: "unknown" if pd.isna(v) else str(int(v))))
        lines += ["The results version (`sdp_cli.RESULTS_VERSION`: what a run measures) is the run's own record since "
                  "version 4, before that the version of its revision's code.", "",
                  "| task | method | seeds | iterations | revision | results version |", "|---|---|---|---|---|---|"]
    else:
        lines += ["| task | method | seeds | iterations | revision |", "|---|---|---|---|---|"]
    for key, g in revs.groupby(["task", "method", "git_rev"] + (["results_version"] if versions else [])):
        its = _ints(g.iteration)
        seeds = _ints(g.train_seed) or "n/a"
        lines.append(f"| {key[0]} | {key[1]} | {seeds} | {its} | `{key[2]}` |" + (f" {key[3]} |" if versions else ""))
    return lines


def _index(df: pd.DataFrame, runs: Path, out: Path, experiment: str | None, files: list[Path],
           carried: list[str], stage: Path, hidden: int = 0) -> Path:
    """README.md of the report in ``out``, written into ``stage``; ``df``: its rows with methods named as drawn
    (:func:`method_variants`); ``files``: the report's, in ``stage`` or kept in ``out``; ``hidden``: runs not
    drawn (:func:`newest_version`)."""
    budgets = (df.groupby(["task", "method"]).agg(
        seeds=("train_seed", _ints),
        n_traj=("n_traj", _ints),
        epochs=("epochs", _ints),
        iterations=("iteration", lambda s: int(s.max()) + 1),
        n_test=("n", "max"), t_a=("t_a", lambda s: ",".join(str(v) for v in sorted(set(s.dropna()))))).reset_index())
    name = experiment or runs.name
    spec = Path("pipelines") / f"{name}.yaml"
    source = (f"from the experiment `{name}` (see `pipelines/{name}.yaml`)." if spec.is_file()
              else f"from the runs in `{runs}` (no `pipelines/{name}.yaml`: e.g. `sdp loop` runs).")
    lines = [f"# Results: {name}", "",
             f"Produced by `sdp report --runs {runs} --out {out}{' --keep-missing' if carried else ''}` with the code of commit `{code_revision()}`", source, "",
             "## Budgets (seeds, dataset sizes, epochs, loop iterations, test instances)", "",
             "| task | method | seeds | n_traj | epochs | iterations | n_test | T_a |", "|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(str(v) for v in r) + " |" for r in budgets.itertuples(index=False)]
    if spec.is_file():
        saved = out.parent / "estimates" / f"{name}.txt"     # results/estimates/, beside the report
        lines += coverage_lines(df, name, hours=estimated_hours(saved), hours_from=f"../estimates/{saved.name}")
    if hidden:
        lines += ["", f"Not drawn: {hidden} run(s) of an older results version than other runs of their task and TO "
                  "family (all_runs.csv keeps their rows; the figures and the ledger read the newest version only)."]
    lines += list(carried)
    lines += revision_lines(df)
    lines += ["", "## Files", ""]
    lines += [f"- `{p.name}`" for p in files if p.parent in (out, stage)]
    n_curves = sum(1 for p in files if p.parent in (out / "curves", stage / "curves"))
    n_loop = sum(1 for p in files if p.parent in (out / "loop", stage / "loop"))
    if n_curves or n_loop:
        lines.append(f"- `curves/` ({n_curves} files: training curves per run and iteration, thinned to <= 500 rows) "
                     f"and `loop/` ({n_loop} files: costs and success per iteration, per task and method): data "
                     f"series for `dvc plots show`")
    if (out / "NOTES.md").is_file():
        lines += ["", "Notes on this run (how it was run, what did not finish): [NOTES.md](NOTES.md)."]
    return atomic_write_bytes(stage / "README.md", lambda f: f.write(("\n".join(lines) + "\n").encode()))

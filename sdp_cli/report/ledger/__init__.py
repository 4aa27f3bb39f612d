"""``results/PAPER.md``: every claim of the paper beside our number, regenerated from the reports.

The ledger reads what ``sdp report`` wrote, never a run folder: ``results/<experiment>/all_runs.csv``
(one row per run, iteration and T_a), ``results/bench/*.csv`` (speed ratios measured side by side by
the ``bench/`` scripts), ``results/estimates/*.txt`` (saved ``sdp pipeline NAME --estimate`` tables: the
hours of runs not made) and ``results/claims.yaml`` (hand-written: each claim's text, the paper's number,
the checks that judge it, why it is not run and the notes that explain a difference; the thresholds shared by
every check are its top-level ``rules``). A claim is data: a list of checks, each of a few kinds
(:mod:`sdp_cli.report.ledger.checks`: ``reaches``, ``solves``, ``ratio``, ``degradation``, ``share``, ``within``,
``near``, ``show``) that select rows of one report and judge them with the typed results of
:mod:`sdp_cli.report.ledger.kinds`; one verdict per claim from its checks' parts
(:func:`sdp_cli.report.ledger.base.claim_verdict`), the same for every claim:

- a quantity is the mean over seeds with a 95% interval (normal approximation, :func:`mean_ci`);
- a ratio claim r_paper > 1 is *reproduced* when ours keeps at least half of the paper's effect,
  ``r - 1 >= (r_paper - 1) / 2``; *partly* with at least a tenth of it; otherwise *not reproduced*;
  a range claim ("2-20x") is reproduced from its lower end;
- a claim none of whose reports exists is *not run*, with the estimate of ``results/estimates/``;
  one with only part of its runs says *partly* and which part is missing;
- a report with runs of two TO families (``to``: fatrop's multiple shooting, box-FDDP, the paper's family) is
  judged per family, and a claim that needs it gives both, with one verdict where they agree;
- every row names the results version (:data:`sdp_cli.RESULTS_VERSION`, :mod:`sdp_cli.report.versions`) of the
  runs it reads, and the header says what changed since the oldest of them (:data:`sdp_cli.RESULTS_HISTORY`):
  a verdict on runs of an older version is what those runs measured, not what the current code does; where a
  task under one TO family has runs of several versions (a re-run filling in), only the newest are read
  (:func:`sdp_cli.report.rows.newest_version`).

The diffusion policies' rows are those at the T_a evaluated at every loop iteration (the training
T_a); "solves" means a success rate of at least 50% over the test instances.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from sdp_cli.families import DEFAULT_TO
from sdp_cli.data.artifacts import atomic_write_bytes
from sdp_cli.errors import SdpError
from sdp_cli.report.ledger.checks import claim_checks, experiments, judge_claim
from sdp_cli.report.ledger.verdicts import Row
from sdp_cli.report.ledger.verdicts import pct_text
from sdp_cli.report.rows import TO_FAMILIES, last_iteration, newest_version, to_family, unfinished
from sdp_cli.report.estimates import read_estimate
from sdp_cli.report.versions import version_text
from sdp_cli import RESULTS_HISTORY, RESULTS_VERSION


def load_results(results: Path) -> dict[str, pd.DataFrame]:
    """``{experiment: all_runs.csv}``, ``{"bench/<name>": csv}`` and ``{"estimates/<experiment>": the saved
    --estimate table}`` under ``results``. A report's rows whose TO family (``to``) is not fatrop's multiple
    shooting are ``{"<experiment>/<family>": rows}`` (``fig2/ddp``: the loop with box-FDDP as its TO), so that
    a rule judges one family at a time; rows without the column are ``ms``."""
    out = {}
    for p in sorted(results.glob("*/all_runs.csv")):
        df = newest_version(pd.read_csv(p))
        fam = to_family(df)
        for f in sorted(set(fam) - {DEFAULT_TO}):
            out[f"{p.parent.name}/{f}"] = df[fam == f].reset_index(drop=True)
        if (fam == DEFAULT_TO).any() or df.empty:
            out[p.parent.name] = df[fam == DEFAULT_TO].reset_index(drop=True)
    for p in sorted((results / "bench").glob("*.csv")):
        out[f"bench/{p.stem}"] = pd.read_csv(p)
    for p in sorted((results / "estimates").glob("*.txt")):
        if len(est := read_estimate(p)):
            out[f"estimates/{p.stem}"] = est
    return out


def _available(c: dict, res) -> bool:
    """Whether one of the reports claim ``c``'s checks read exists."""
    return any(e in res for e in experiments(c))


def _shared(key: str) -> bool:
    return key.startswith(("bench/", "estimates/"))


def _family_results(res: dict[str, pd.DataFrame], fam: str) -> dict[str, pd.DataFrame]:
    """``res`` as a rule sees the TO family ``fam``: each report's rows of that family under the report's name
    (reports without such rows absent), the bench results and estimates as they are."""
    out = {k: v for k, v in res.items() if _shared(k)}
    out.update({k[: -len(fam) - 1]: v for k, v in res.items() if not _shared(k) and k.endswith("/" + fam)})
    return out


def not_run_text(c: dict, res: dict) -> str:
    """Why claim ``c`` is *not run* (its ``not_run``, hand-written, without numbers of ours) and, per experiment
    it needs that has no report, the runs and hours of its saved estimate (``estimates/<experiment>`` in ``res``:
    ``"fig2: 40 runs, 20.5 h in one process (sdp pipeline fig2 --estimate, results/estimates/fig2.txt)"``)."""
    hours = []
    for exp in experiments(c):
        est = res.get(f"estimates/{exp}")
        if exp not in res and est is not None and "total_cpu_h" in est:
            hours.append(f"{exp}: {len(est)} runs, {est.total_cpu_h.sum():.1f} h in one process "
                         f"(`sdp pipeline {exp} --estimate`, results/estimates/{exp}.txt)")
    return "; ".join(x for x in (str(c.get("not_run", "")).strip().rstrip("."), *hours) if x)


def _judge(c: dict, res: dict, rules: dict | None, loop_to: str | None = None) -> Row:
    cid = int(c["id"])
    if not _available(c, res):
        return Row("", "not run", not_run_text(c, res))
    try:
        return judge_claim(c, res, rules, {"loop_to": loop_to} if loop_to else {})
    except (KeyError, AttributeError) as e:    # a column missing from an older report
        raise SdpError(f"claim {cid}: the reports lack {e} (re-run `sdp report` on the runs)") from None


def _reports(c: dict, res: dict) -> list[pd.DataFrame]:
    """The report rows claim ``c`` needs that ``res`` holds (bench results and estimates left out)."""
    return [res[e] for e in experiments(c) if e in res and not _shared(e)]


def _judge_family(c: dict, res: dict, rules: dict | None, fam: str) -> Row:
    """:func:`_judge` on the TO family ``fam``'s reports (the rules name the loop's TO by the family's solver),
    which may hold only runs partway (a re-run filling up): *not run* until one of its runs has reached its
    loop's final iteration, naming the runs partway."""
    reports = _reports(c, res)
    if reports and all(last_iteration(d).empty for d in reports):
        return Row("partway (no run finished yet)", "not run", "; ".join(u for u in map(unfinished, reports) if u))
    return _judge(c, res, rules, TO_FAMILIES.get(fam, fam))


def _run_versions(c: dict, res: dict) -> list[float]:
    """The results version of every row claim ``c`` reads: the rows of the reports its checks read, of its one task
    where every check selects that one (``where: {task: ...}``) (NaN: unknown; empty: a bench)."""
    tasks = {(s.get("where") or {}).get("task") for s in c["checks"] if isinstance(s, dict)}
    task = tasks.pop() if len(tasks) == 1 else None
    rows = [d[d["task"] == task] if task and "task" in d else d for d in _reports(c, res)]
    return [v for d in rows for v in (d["results_version"] if "results_version" in d else [float("nan")] * len(d))]


def ledger_rows(res: dict[str, pd.DataFrame], claims: list[dict], rules: dict | None = None) -> list[dict]:
    """One row per claim: its checks (``checks:``) on ``res`` over the shared thresholds ``rules``, or *not run* when
    none of the reports they read exists. Where the reports it needs
    also hold runs of another TO family (:func:`load_results`), the rule judges each family apart and the row
    gives both (``TO by fatrop: ...; TO by box-FDDP: ...``), with one verdict where they agree. ``runs``: the
    results versions of the rows read (per family where they differ: ``1 (fatrop); 4 (box-FDDP)``), ``versions``
    the known ones as a set."""
    others = sorted({k.rsplit("/", 1)[1] for k in res if "/" in k and not _shared(k)})
    rows = []
    for c in claims:
        row = _judge(c, res, rules)
        fams = [f for f in others if _available(c, _family_results(res, f))
                and any(f"{e}/{f}" in res for e in experiments(c))]
        more = [(f, _judge_family(c, _family_results(res, f), rules, f)) for f in fams]
        versions = [(DEFAULT_TO, _run_versions(c, res))] + [(f, _run_versions(c, _family_results(res, f))) for f in fams]
        texts = [(f, version_text(vs) if vs else "") for f, vs in versions]
        if more:
            parts = [(DEFAULT_TO, row)] + more
            name = lambda f: TO_FAMILIES.get(f, f)   # noqa: E731
            row = Row("; ".join(f"TO by {name(f)}: {r.ours or '—'}" for f, r in parts),
                      parts[0][1].verdict if len({r.verdict for _, r in parts}) == 1 else
                      "; ".join(f"{r.verdict} ({name(f)})" for f, r in parts),
                      " ".join(f"TO by {name(f)}: {r.detail.rstrip('.')}." for f, r in parts if r.detail),
                      row.rule)
        runs = (texts[0][1] if len({t for _, t in texts}) == 1 else
                "; ".join(f"{t or '—'} ({TO_FAMILIES.get(f, f)})" for f, t in texts))
        known = {int(v) for _, vs in versions for v in vs if pd.notna(v)}
        rows.append({**c, "ours": row.ours, "verdict": row.verdict, "detail": row.detail, "rule": row.rule, "runs": runs,
                     "versions": known})
    return rows


def read_claims(path: Path) -> tuple[list[dict], dict]:
    """``(claims, rules)`` of a claims file; every claim has ``checks``, each a kind of
    :data:`sdp_cli.report.ledger.checks.CHECKS` with valid fields (checked here, before any report is read)."""
    import yaml

    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SdpError(f"cannot read the claims file {path}: {e}") from None
    claims = (spec or {}).get("claims") if isinstance(spec, dict) else None
    need = {"id", "claim", "paper", "checks"}
    if not isinstance(claims, list) or not all(isinstance(c, dict) and need <= set(c) for c in claims):
        raise SdpError(f"{path}: expected `claims:` a list of entries with {', '.join(sorted(need))}")
    rules = spec.get("rules") or {}
    if not isinstance(rules, dict):
        raise SdpError(f"{path}: rules must be a mapping")
    for c in claims:
        try:
            claim_checks(c, rules)
        except SdpError as e:
            raise SdpError(f"{path}: {e}") from None
    return claims, rules


def _share(x: float) -> str:
    return {0.5: "half", 0.1: "a tenth"}.get(x, pct_text(x))


def _version_lines(rows: list[dict]) -> list[str]:
    """The header's paragraph on results versions: the current one, and what changed after the oldest one
    a row reads (:data:`sdp_cli.RESULTS_HISTORY`)."""
    used = set().union(*(r["versions"] for r in rows))
    lines = [f"Results version now: {RESULTS_VERSION} (`sdp_cli.RESULTS_VERSION`, what a run measures). The column "
             "*runs' results version* gives the version of the runs each row reads (recorded by a run since "
             "version 4, before that the version of its code revision); a verdict on runs of an older version is "
             "what those runs measured, not what the current code does, until they are re-made."]
    newer = [v for v in sorted(RESULTS_HISTORY) if used and min(used) < v <= RESULTS_VERSION]
    if newer:
        lines += ["", "What changed since the oldest of them:", ""]
        lines += [f"- version {v}: {RESULTS_HISTORY[v]}." for v in newer]
    return lines + [""]


def write_ledger(path: str | Path, claims_file: str | Path | None = None) -> Path:
    """Write the ledger ``path`` (``results/PAPER.md``) from the reports in its folder."""
    path = Path(path)
    results = path.parent
    claims, rules = read_claims(Path(claims_file) if claims_file else results / "claims.yaml")
    res = load_results(results)
    rows = ledger_rows(res, claims, rules)
    lines = ["# The paper's claims beside our numbers", "",
             "Written by `sdp report --ledger results/PAPER.md` from `results/*/all_runs.csv`, `results/bench/*.csv`,",
             "`results/estimates/*.txt` (hours of runs not made) and `results/claims.yaml` (the claims, the paper's",
             "numbers and the notes); do not edit by hand.",
             "Rules (the same for every claim, `sdp_cli/report/ledger/base.py`): means over seeds with 95% intervals; a",
             f"ratio claim is *reproduced* when ours keeps at least {_share(rules['keep'])} of the paper's effect (r - 1), "
             "*partly* with",
             f"at least {_share(rules['partly'])} of it; a policy *solves* a task at >= {pct_text(rules['solved'])} "
             "success; runs that have not reached the",
             "final iteration are left out and named; *not run* gives the estimate.", ""]
    lines += _version_lines(rows)
    lines += ["| # | claim | where | paper | ours | runs' results version | verdict |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['id']} | {r['claim']} | {r.get('where', '')} | {r['paper']} | {r['ours'] or '—'} | "
                     f"{r['runs'] or '—'} | **{r['verdict']}** |")
    lines += ["", "## Notes per claim", ""]
    for r in rows:
        text = " ".join(x.rstrip(".") + "." for x in (r["detail"], r["rule"] and f"Rule: {r['rule']}",
                                                      str(r.get("notes", "")).strip()) if x)
        if text:
            lines.append(f"- **{r['id']}.** {text}")
    used = {e for c in claims for e in experiments(c)}
    exps = sorted(k for k in res if k in used and not k.startswith("bench/"))
    lines += ["", "Reports read: " + (", ".join(f"[{e}]({e}/README.md)" for e in exps) or "none") + "; "
              + (", ".join(f"`{k}.csv`" for k in sorted(res) if k.startswith("bench/")) or "no bench results") + "."]
    return atomic_write_bytes(path, lambda f: f.write(("\n".join(lines) + "\n").encode()))

"""The kinds of check a claim of results/claims.yaml is made of, by name (:data:`CHECKS`). Every kind reads its
rows the same way (:class:`~sdp_cli.report.ledger.base.Check`'s ``experiment``, ``method``, ``where``, ``at``,
``per``) and judges them with a typed result of :mod:`sdp_cli.report.ledger.kinds`:

- ``reaches``: the first dataset size from which a method's mean cost stays within a share of TO alone's
  (:class:`FirstN`), per task; with ``against``, the ratio of another method's first size over it;
- ``solves``: a success rate at least the ``solved`` line (or not, ``solves: false``), with comparisons to another
  method (``beats``, ``no_worse``) and between columns (``less``, ``at_most``), per group; or the best over a column
  (``best_over``), or the values of a column where it solves (``window``);
- ``ratio``: per-seed ratios of two columns, each within one evaluation (one row), against the paper's (:class:`Ratio`);
- ``degradation``: the worst mean of a column over a high range of another over the worst over a low range;
- ``share``: the share of rows with an event (``above``), or one minus a rate (``complement``), at least a line,
  for every one of ``methods`` and more than for ``than``;
- ``within``: a mean within a share of another selection's (:class:`Within`);
- ``near``: a bench's value within a tolerance of the paper's, per bench row;
- ``show``: columns shown beside the verdict, never judged.

A column name may hold ``{to}``, expanded per TO baseline of the check's ``baselines`` (:data:`BASELINES`: ``loop``,
the loop's TO, ``{to}`` empty, named by its solver; ``single_shooting``, ``ss_``): the check runs once per baseline,
skipping one a report has no column for."""

from __future__ import annotations

from sdp_cli.errors import SdpError
from sdp_cli.report.ledger.base import Check, build, claim_verdict
from sdp_cli.report.ledger.check_ratios import Degradation, Near, RatioCheck, Share, Show, WithinCheck
from sdp_cli.report.ledger.check_success import Reaches, Solves
from sdp_cli.report.ledger.verdicts import Row
from sdp_cli.report.rows import unfinished


#: every kind of check by the name results/claims.yaml gives it (``kind:``)
CHECKS = {cls.kind: cls for cls in (Reaches, Solves, RatioCheck, Degradation, Share, WithinCheck, Near, Show)}


def claim_checks(c: dict, shared: dict | None = None) -> list[Check]:
    """Claim ``c``'s checks (its ``checks:`` entries over the ``shared`` thresholds)."""
    specs = c.get("checks")
    if not isinstance(specs, list) or not specs:
        raise SdpError(f"claim {c.get('id')}: `checks:` must be a non-empty list of checks")
    return [build(s, shared or {}, CHECKS, f"claim {c.get('id')}, check {i + 1}") for i, s in enumerate(specs)]


def experiments(c: dict) -> list[str]:
    """The reports claim ``c``'s checks read (it is judged where one of them exists)."""
    return list(dict.fromkeys(s.get("experiment") for s in c.get("checks") or [] if isinstance(s, dict)))


def judge_claim(c: dict, res: dict, shared: dict | None = None, ctx: dict | None = None) -> Row:
    """Claim ``c`` on ``res``: its checks' parts (our numbers), one verdict (:func:`claim_verdict`) and the notes:
    what is missing, the runs not finished (left out) and each judged check's rule."""
    ctx = ctx or {}
    checks = claim_checks(c, shared)
    outs = [ch.judge(res, ctx) for ch in checks]
    parts = [p for o in outs for p in o.parts]
    verdict = claim_verdict(parts, [o.parts for ch, o in zip(checks, outs) if ch.required],
                            any(o.incomplete for o in outs))
    loops = dict.fromkeys(ch.experiment for ch in checks if ch.at in ("last_iteration", "sweep", "loop"))
    notes = [n for o in outs for n in o.notes] + [unfinished(res[e]) for e in loops if e in res]
    rules = list(dict.fromkeys(r for ch in checks if ch.judged and (r := ch.rule())))
    return Row("; ".join(p.text for p in parts), verdict, "; ".join(n for n in notes if n), "; ".join(rules))

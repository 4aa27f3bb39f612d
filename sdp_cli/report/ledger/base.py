"""A claim of the ledger is a list of *checks* (results/claims.yaml), each of a few kinds
(:mod:`sdp_cli.report.ledger.checks`). A check reads rows of one report (:class:`~sdp_cli.report.ledger.select.
Selection`) and returns an :class:`Outcome`: typed :class:`Part` s, one per group it judges (a task, a loop, a TO
baseline), each with its prose and verdict, and what it could not judge. :func:`claim_verdict` makes one verdict
of a claim's parts, the same for every claim."""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
from typing import ClassVar

from sdp_cli.errors import SdpError
from sdp_cli.report.ledger.select import AT, Selection
from sdp_cli.report.ledger.verdicts import VERDICTS, combine
from sdp_cli.report.rows import method_label

#: a part shown beside the judged ones, never judged
SHOWN = "shown"
#: the thresholds a kind may leave unset (``None``) in a check, to take from results/claims.yaml's shared ``rules``
THRESHOLDS = ("solved", "within", "keep", "partly")


@dataclass(frozen=True)
class Part:
    """One judged (or shown) group of a check: its prose and its verdict (:data:`VERDICTS` or :data:`SHOWN`)."""
    text: str
    verdict: str


@dataclass
class Outcome:
    """What a check found: its parts, notes for the claim's notes column (what is missing, the rule), and
    ``incomplete``: a group the claim needs has no verdict yet (the claim is then *partly* at best)."""
    parts: list[Part] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    incomplete: bool = False


@dataclass(frozen=True, kw_only=True)
class Check:
    """The fields every kind has. ``experiment``: the report read; ``method``: the method judged; ``where``, ``at``:
    which of its rows (:class:`Selection`); ``per``: judged per group of these columns (``[task]``: per task);
    ``expect``: the groups the claim needs (a group per entry, its values in ``per``'s order; a single value for a
    single column): one without a verdict leaves the claim *partly* at best and is named with the hours of its
    runs where ``results/estimates/<experiment>.txt`` has them; ``label``: the words before the check's numbers;
    ``required``: the claim is *not reproduced* when this check is, *not run* when it is; ``judged``: false to show
    the numbers only."""
    kind: ClassVar[str] = ""
    experiment: str
    method: str | None = None
    where: dict = field(default_factory=dict)
    at: str = "last_iteration"
    per: list = field(default_factory=list)
    expect: list = field(default_factory=list)
    label: str = ""
    required: bool = False
    judged: bool = True

    def __post_init__(self):
        if self.at not in AT:
            raise SdpError(f"at: {self.at!r} is not one of {', '.join(AT)}")
        for name in ("where",):
            if not isinstance(getattr(self, name), dict):
                raise SdpError(f"{name} must be a mapping")
        for name in ("per", "expect"):
            if not isinstance(getattr(self, name), list):
                raise SdpError(f"{name} must be a list")
        self.validate()

    def validate(self) -> None:
        """A kind's own rules on its fields (raise :class:`SdpError`)."""

    @property
    def selection(self) -> Selection:
        return Selection(self.experiment, self.method, self.where, self.at)

    @property
    def name(self) -> str:
        """The judged method as the paper names it (``SDP``), with the selection's values (``SDP at n_traj 3``)."""
        return (method_label(self.method) if self.method else "") + self.selection.where_text()

    def expected(self) -> list[tuple]:
        return [tuple(e) if isinstance(e, list) else (e,) for e in self.expect]

    def judge(self, res: dict, ctx: dict) -> Outcome:     # pragma: no cover - every kind overrides it
        raise NotImplementedError

    def rule(self) -> str:
        """The check's rule in words, for the claim's notes ("" for a check shown only)."""
        return ""

    def verdict(self, holds: bool) -> str:
        return SHOWN if not self.judged else "reproduced" if holds else "not reproduced"


def build(spec: dict, shared: dict, registry: dict, where: str) -> Check:
    """A check from its yaml entry ``spec`` (``kind:`` and the kind's fields), its unset thresholds from ``shared``
    (results/claims.yaml's ``rules``): an unknown kind or field, a field missing or a wrong value is one
    :class:`SdpError` naming ``where`` (``"claim 3, check 2"``)."""
    if not isinstance(spec, dict) or "kind" not in spec:
        raise SdpError(f"{where}: expected a mapping with `kind:` (one of {', '.join(sorted(registry))})")
    cls = registry.get(spec["kind"])
    if cls is None:
        raise SdpError(f"{where}: unknown kind {spec['kind']!r}; known: {', '.join(sorted(registry))}")
    known = {f.name: f for f in fields(cls)}
    extra = sorted(set(spec) - set(known) - {"kind"})
    if extra:
        raise SdpError(f"{where} ({cls.kind}): unknown field {extra[0]!r}; known: {', '.join(sorted(known))}")
    values = {k: v for k, v in spec.items() if k != "kind"}
    for name, f in known.items():
        if values.get(name) is None and name in shared and f.default is None:
            values[name] = shared[name]
        absent = (name not in values and f.default is MISSING and f.default_factory is MISSING or
                  name in THRESHOLDS and f.default is None and values.get(name) is None)
        if absent:
            raise SdpError(f"{where} ({cls.kind}): results/claims.yaml gives no {name!r} "
                           "(in the check or the shared rules)")
    try:
        check = cls(**values)
    except SdpError as e:
        raise SdpError(f"{where} ({cls.kind}): {e}") from None
    except TypeError as e:
        raise SdpError(f"{where} ({cls.kind}): {e}") from None
    return check


def claim_verdict(parts: list[Part], required: list[list[Part]], incomplete: bool) -> str:
    """One verdict from a claim's judged parts (shown ones and *not run* ones left aside): *reproduced* when all are,
    *not reproduced* when all are not, else *partly* (:func:`combine`); *partly* at best while a group it needs has
    no verdict (``incomplete``); *not reproduced* when a ``required`` check's part is, *not run* when a required
    check has no judged part or no part is judged."""
    judged = [p.verdict for p in parts if p.verdict in VERDICTS and p.verdict != "not run"]
    if not judged or any(not any(p.verdict in VERDICTS and p.verdict != "not run" for p in r) for r in required):
        return "not run"
    if any(p.verdict == "not reproduced" for r in required for p in r):
        return "not reproduced"
    v = combine(judged)
    return "partly" if incomplete and v == "reproduced" else v

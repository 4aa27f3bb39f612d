"""Which evaluation rows a figure or a claim reads: the one place where rows are selected.

Rows are ``all_runs.csv``'s (:func:`sdp_cli.report.runs.load_runs`): one per run, iteration, T_a and
evaluated checkpoint. The figures draw a method's *variants* apart (:func:`method_variants`) and most of them
one budget per method (:func:`largest_budget`); loops are read at the T_a evaluated at every iteration
(:func:`loop_t_a`); the ledger reads a loop's final iteration (:func:`last_iteration`), names the runs that
have not reached it (:func:`unfinished`) and averages per seed (:func:`per_seed`, :func:`mean_ci`). Variants are
named in legends and the ledger as the paper names its methods (:func:`method_label`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from sdp_cli import RESULTS_SCOPE
from sdp_cli.families import DEFAULT_TO, TO_NAMES


def mean_ci(values: pd.Series) -> tuple[float, float, int]:
    """Mean and 95% confidence half-width (normal approximation over seeds) of finite values;
    the mean is +inf if any value is infinite (a diverged seed); the half-width is NaN (no
    interval) with fewer than two seeds."""
    v = np.asarray(values, dtype=float)
    if np.any(np.isinf(v)):
        return float("inf"), float("nan"), len(v)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan"), 0
    half = 1.96 * v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else float("nan")
    return float(v.mean()), float(half), int(v.size)


def per_seed(d: pd.DataFrame, col: str) -> pd.Series:
    """``col`` averaged per training seed (the unit every interval is over)."""
    return d.groupby("train_seed")[col].mean()


def first_rows(df: pd.DataFrame) -> pd.DataFrame:
    """Each run's rows at its first evaluated iteration (where its loop T_a and first dataset are read)."""
    return df[df.iteration == df.groupby("run").iteration.transform("min")]


def loop_t_a(d: pd.DataFrame) -> pd.DataFrame:
    """Rows at the T_a evaluated at every iteration of a run (the last one adds Table 2c's sweep)."""
    keep = []  # (load_runs gives every row an integer iteration)
    by = ["run"] if "run" in d else ["method", "train_seed"]   # (Fig. 3: one run per (T_h, T_a) and seed)
    for _, g in d.groupby(by, dropna=False):
        common = set.intersection(*(set(x.t_a) for _, x in g.groupby("iteration")))
        keep.append(g[g.t_a.isin(common)])
    return pd.concat(keep) if keep else d


class Variant(str):
    """A drawn variant of a method: its key (``sdp-K2``, ``sdp-h32-ta16``, ``sdp-conv-track-to-ddp``) as a ``str``, so
    that figures group, sort, colour, label and name files by it, and its parts as typed fields, set by
    :func:`method_variants` from ``all_runs.csv``'s columns and read by the helpers below (never parsed back from
    the key): ``method`` (the plain method), ``k`` (the rollout's diffusion steps, the K ablation), ``pair``
    (``(T_h, T_a)``, Fig. 3), ``conversion`` (of predicted chunks, :mod:`sdp_cli.tasks.conversion`) and ``to``
    (the loop's TO family). A plain string is the plain method (:func:`as_variant`)."""

    method: str
    k: int | None
    pair: tuple[int, int] | None
    conversion: str | None
    to: str | None

    def __new__(cls, method: str, k: int | None = None, pair: tuple[int, int] | None = None,
                conversion: str | None = None, to: str | None = None):
        key = (str(method) + (f"-K{k}" if k is not None else "") + (f"-h{pair[0]}-ta{pair[1]}" if pair else "")
               + (f"-conv-{CONVERSION_TAGS.get(conversion, conversion)}" if conversion else "")
               + (f"-to-{to}" if to else ""))
        self = super().__new__(cls, key)
        self.method, self.k, self.conversion, self.to = str(method), k, conversion, to
        self.pair = tuple(pair) if pair else None
        return self

    def __reduce__(self):
        return Variant, (self.method, self.k, self.pair, self.conversion, self.to)

    def replace(self, **parts) -> "Variant":
        """This variant with some parts changed (``v.replace(to=None)``: the variant without its TO family)."""
        now = {"k": self.k, "pair": self.pair, "conversion": self.conversion, "to": self.to}
        return Variant(self.method, **{**now, **parts})


def as_variant(method) -> Variant:
    """``method`` as a :class:`Variant`: itself, or a plain method (no variant parts) for a plain string."""
    return method if isinstance(method, Variant) else Variant(str(method))


def typed_like(methods: pd.Series, drawn) -> pd.Series:
    """Keys read back from an earlier report's CSV (plain strings: ``sdp-to-ddp``) as the :class:`Variant` drawn
    now under the same key (``drawn``: the methods of the rows drawn now); a key not drawn now stays a plain
    method."""
    now = {str(v): v for v in drawn if isinstance(v, Variant)}
    return methods.map(lambda m: now.get(str(m), m))


def method_variants(df: pd.DataFrame) -> pd.DataFrame:
    """For the figures: where one task has runs of a method that differ in how the policy acts, the
    variants are drawn and tabulated apart instead of averaged together (all_runs.csv keeps the plain
    method and the typed columns this reads): ``method`` becomes each row's :class:`Variant`, whose parts are
    set where they vary within the task: several diffusion step counts (``k_rollout``, the K ablation:
    ``<method>-K<k>``); several (T_h, T_a) pairs (Fig. 3; T_a the run's loop T_a, the one evaluated at its
    first iteration: ``<method>-h<T_h>-ta<T_a>``); several conversions of predicted chunks (``conversion``:
    ``<method>-conv-<tag>``, :data:`CONVERSION_TAGS`; chunked rows evaluated before the column existed used
    ``inverse-dynamics``); several TO families (``to``: collection, refinement and TO alone by ``ms`` or ``ddp``,
    so that TO alone and refined are drawn per family; rows evaluated before the column existed are ``ms``:
    ``<method>-to-<family>``)."""
    if df.empty:
        return df
    df = df.copy()
    parts = pd.DataFrame({"k": None, "pair": None, "conversion": None, "to": None}, index=df.index, dtype=object)
    if "k_rollout" in df:
        ks = df.groupby(["task", "method"]).k_rollout.transform("nunique")
        mixed = (ks > 1) & df.k_rollout.notna()
        parts.loc[mixed, "k"] = df.loc[mixed, "k_rollout"].astype(int)
    if {"horizon", "t_a", "run", "iteration"} <= set(df.columns):
        run_t_a = df.run.map(first_rows(df).groupby("run").t_a.min())
        pair = df.horizon.astype("Int64").astype(str) + "-ta" + run_t_a.astype("Int64").astype(str)
        with_k = df.method.astype(str) + parts.k.map(lambda k: "" if k is None else f"-K{k}")   # (per K variant)
        mixed = (pair.groupby([df.task, with_k]).transform("nunique") > 1) & df.horizon.notna() & run_t_a.notna()
        parts.loc[mixed, "pair"] = pd.Series([(int(h), int(t)) for h, t in zip(df.horizon[mixed], run_t_a[mixed])],
                                             index=df.index[mixed], dtype=object)
    if "conversion" in df:
        conv = row_conversions(df)
        mixed = (conv.groupby(df.task).transform("nunique") > 1) & conv.notna()
        parts.loc[mixed, "conversion"] = conv[mixed]
    if "to" in df:
        fam = to_family(df)
        mixed = fam.groupby(df.task).transform("nunique") > 1
        parts.loc[mixed, "to"] = fam[mixed]
    df["method"] = [Variant(m, k, p, c, t) for m, k, p, c, t in
                    zip(df.method, parts.k, parts.pair, parts.conversion, parts.to)]
    return df


#: a conversion's tag in variant names (``sdp-conv-track``) and its name in legends
CONVERSION_TAGS = {"inverse-dynamics": "invdyn", "tracking": "track"}
CONVERSION_NAMES = {"invdyn": "inverse dynamics", "track": "tracking"}


def row_conversions(df: pd.DataFrame) -> pd.Series:
    """Each row's conversion of predicted chunks: the ``conversion`` column, and ``inverse-dynamics`` for chunked
    rows (``k_rollout`` set) evaluated before the column existed; NaN for rows that act on the controls."""
    conv = df["conversion"].astype(object)
    chunked = df["k_rollout"].notna() if "k_rollout" in df else conv.notna()
    return conv.where(conv.notna() | ~chunked, "inverse-dynamics")


def conversion_text(rows: pd.DataFrame) -> str:
    """``" (tracking)"``: how the chunked rows ``rows`` (one task) turned predicted chunks into controls, for a
    ledger row to name beside the task; ``""`` where no row records a conversion (a task whose policies act
    on the controls). Chunked rows evaluated before the column existed used one-step inverse dynamics."""
    if "conversion" not in rows or not rows["conversion"].notna().any():
        return ""
    names = [CONVERSION_NAMES.get(CONVERSION_TAGS.get(c, c), c) for c in sorted(set(row_conversions(rows).dropna()))]
    return f" ({', '.join(names)})" if names else ""


def split_conversion(method) -> tuple[Variant, str | None]:
    """``(variant without its conversion, conversion tag)``: ``sdp-conv-track`` -> ``("sdp", "track")``."""
    v = as_variant(method)
    return v.replace(conversion=None), (CONVERSION_TAGS.get(v.conversion, v.conversion) if v.conversion else None)


#: how reports name a TO family (``to`` of the evaluations); ``ms`` is the main one
TO_FAMILIES = TO_NAMES


def to_family(df: pd.DataFrame) -> pd.Series:
    """Each row's TO family, the loop's TO (column ``to``: ``ddp`` for box-FDDP); ``ms`` (fatrop's multiple
    shooting) where the column is empty or absent (runs made before the DDP solver existed)."""
    if "to" not in df:
        return pd.Series(DEFAULT_TO, index=df.index, dtype=object)
    return df["to"].astype(object).where(df["to"].notna(), DEFAULT_TO).astype(str)


def newest_version(df: pd.DataFrame) -> pd.DataFrame:
    """The rows the figures and the ledger read: where a task under one TO family has rows of several results
    versions (``results_version``, :mod:`sdp_cli.report.versions`), a row of an older version only where no
    version since its own touches it (:data:`sdp_cli.RESULTS_SCOPE`; a version without a scope touches every
    row). A re-run fills a report run by run while the earlier report's rows are kept (``--keep-missing``);
    between versions a task may have been redefined (UR5(0, 0)'s TO-alone cost is 0.059 at version 1 and 6.28
    at version 4), so one curve or interval mixing them would measure nothing; the MLPs' quadrotor rows of
    version 4 stay beside the diffusion policies' re-run at version 7 (versions 5-7 changed nothing they
    measure). Rows of an unknown version are kept; ``all_runs.csv`` and the coverage table keep every row."""
    return df[newest_version_mask(df)]


def touched_by(version: int, rows: pd.DataFrame) -> pd.Series:
    """Which of ``rows`` results version ``version``'s change touches (:data:`sdp_cli.RESULTS_SCOPE`)."""
    if version not in RESULTS_SCOPE:
        return pd.Series(True, index=rows.index)
    method = rows["method"].map(plain_method) if "method" in rows else pd.Series("", index=rows.index)
    out = pd.Series(False, index=rows.index)
    for alt in RESULTS_SCOPE[version]:
        hit = pd.Series(True, index=rows.index)
        if "methods" in alt:
            hit &= method.isin(alt["methods"])
        if "task_prefix" in alt:
            hit &= rows["task"].astype(str).str.startswith(alt["task_prefix"])
        if "to" in alt:
            hit &= to_family(rows).isin(alt["to"])
        if "min_n_algo" in alt:
            n = pd.to_numeric(rows["n_algo"], errors="coerce") if "n_algo" in rows else pd.Series(np.nan, index=rows.index)
            hit &= ~(n < alt["min_n_algo"])      # unknown: touched
        out |= hit
    return out


def newest_version_mask(df: pd.DataFrame) -> pd.Series:
    """:func:`newest_version`'s rows as a boolean mask over ``df``."""
    if df.empty or "results_version" not in df or "task" not in df:
        return pd.Series(True, index=df.index)
    v = pd.to_numeric(df["results_version"], errors="coerce")
    newest = v.groupby([df["task"], to_family(df)]).transform("max")
    keep = ~(v < newest)
    for old in sorted(set(v[~keep].dropna().astype(int))):
        rows = df[(v == old) & ~keep]
        later = range(old + 1, int(newest[rows.index].max()) + 1)
        touched = pd.Series(False, index=rows.index)
        for w in later:     # touched by a version after its own, up to its task's newest
            touched |= touched_by(w, rows) & (w <= newest[rows.index])
        keep[rows.index] = ~touched
    return keep


def split_family(method) -> tuple[Variant, str | None]:
    """``(variant without its TO family, family)`` of a drawn variant: ``sdp-to-ddp`` -> ``("sdp", "ddp")``;
    no family part: ``(method, None)``."""
    v = as_variant(method)
    return v.replace(to=None), v.to


def family_of(method) -> str:
    """The TO family of a drawn variant (``sdp-to-ddp`` -> ``ddp``; none: ``ms``)."""
    return as_variant(method).to or DEFAULT_TO


def plain_method(method) -> str:
    """The method a drawn variant is of (``sdp-K5-h32-ta16`` -> ``sdp``)."""
    return as_variant(method).method


def ta_pair(method) -> tuple[int, int] | None:
    """(T_h, T_a) of a variant drawn per pair (``<method>-h<T_h>-ta<T_a>``, with no K part), else None."""
    v = as_variant(method)
    return v.pair if v.k is None else None


PAPER_NAMES = {"pddp_s": "PDDP+S"}    # the paper's name where upper-casing ours does not give it


def method_label(method) -> str:
    """Legend name, the paper's: ``SDP``, ``PDDP+S``, ``SDP-K2``, ``SDP (T_h 32, T_a 16)``, ``SDP (TO box-FDDP)``
    (the loop's TO family by its solver, :data:`TO_FAMILIES`), ``SDP (tracking)``."""
    v = as_variant(method)
    if v.to:
        return f"{method_label(v.replace(to=None))} (TO {TO_FAMILIES.get(v.to, v.to)})"
    if v.conversion:
        tag = CONVERSION_TAGS.get(v.conversion, v.conversion)
        return f"{method_label(v.replace(conversion=None))} ({CONVERSION_NAMES.get(tag, tag)})"
    name = PAPER_NAMES.get(v.method, v.method.upper())
    if v.pair:
        return f"{name} (T_h {v.pair[0]}, T_a {v.pair[1]})"
    return name + (f"-K{v.k}" if v.k is not None else "")


def largest_budget(df: pd.DataFrame) -> pd.DataFrame:
    """The rows behind ``fig2a``, ``fig2b``, ``table2c``, ``traj`` and ``loop/``: per task and method, the rows
    at the most epochs (a run evaluated at several epoch counts has a row per count) of the runs with the
    largest first dataset (n_traj at the run's first iteration). Fig. 1's sweeps would otherwise be averaged
    into one point per iteration whose "seeds" are runs of different budgets; the loops of one budget (Fig. 2-4)
    keep every row. ``fig1`` shows all budgets."""
    if df.empty or not {"run", "iteration", "epochs", "n_traj"} <= set(df.columns):
        return df
    by = [df.task, df.method]
    keep = (df.epochs == df.epochs.groupby(by).transform("max")) | df.epochs.isna()
    first = first_rows(df).groupby("run").n_traj.max()
    n_traj = df.run.map(first).where(keep)
    keep &= (n_traj == n_traj.groupby(by).transform("max")) | df.run.map(first).isna()
    return df[keep]


def final_iteration(d: pd.DataFrame) -> pd.Series:
    """Per task, its loops' final iteration: the last one its runs' ``n_algo`` asks for where the rows
    record it (a loop's rows do; older ones get it from the run's ``loop_config.json``), else the last
    one any of its runs reached."""
    reached = d.groupby("task").iteration.max()
    if "n_algo" not in d:
        return reached
    asked = (d.groupby("task").n_algo.max() - 1).reindex(reached.index)
    return pd.concat([reached, asked], axis=1).max(axis=1)


def last_iteration(d: pd.DataFrame) -> pd.DataFrame:
    """The final loop iteration at the loop's T_a, of the runs that reached it (one row per task, method
    and seed); a task's final iteration is :func:`final_iteration`'s."""
    if not len(d):
        return d
    d = pd.concat([loop_t_a(g) for _, g in d.groupby("task")])
    return d[d.iteration == d.task.map(final_iteration(d))]


def unfinished(d: pd.DataFrame) -> str:
    """``"runs not finished (left out): ..."`` for runs that have not reached their task's final iteration."""
    if not len(d):
        return ""
    last = d.groupby(["task", "run"]).iteration.max()
    final = final_iteration(d)
    todo = sorted(run for (task, run), it in last.items() if it < final[task])
    return f"runs not finished (left out): {', '.join(todo)}" if todo else ""

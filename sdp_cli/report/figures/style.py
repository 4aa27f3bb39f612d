"""How the report's figures and tables look and are written: method colours, markers and legend
order (variants ``<method>-K<k>`` and ``<method>-h<T_h>-ta<T_a>`` included, read from their typed parts), readable log ticks, the Agg
backend, and atomic writes of PNG, CSV and markdown files."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.families import DEFAULT_TO
from sdp_cli.data.artifacts import atomic_write_bytes
from sdp_cli.report.rows import as_variant, split_family, ta_pair

class _Shades(dict):
    """Method -> colour (or marker); a variant ``<method>-K<k>`` or ``<method>-h<T_h>-ta<T_a>``
    (:func:`sdp_cli.report.make.method_variants`) gets its method's: colours darker for K < 5 and lighter
    for K > 5; (T_h, T_a) variants spread from dark to light in (T_h, T_a) order among the methods of the
    same figure (``among``), so that the variants' curves stay apart and each legend entry matches its curve."""

    def get(self, key, default=None, among=()):
        if key in self:
            return self[key]
        base, family = split_family(key)
        if family:    # a TO-family variant: its method's, lighter for a family other than ours (ms)
            value = self.get(base, default, among=[split_family(a)[0] for a in among])
            if not self.shade or value is None or family == DEFAULT_TO:
                return value
            import matplotlib.colors as mc

            return tuple(c + (1 - c) * 0.45 for c in mc.to_rgb(value))
        v = as_variant(key)
        k = v.k if v.pair is None and v.conversion is None else None    # (a K variant alone is shaded by K)
        pair = ta_pair(v)
        if v.method not in self or not (k is not None or pair):
            return default
        value = self[v.method]
        if not self.shade:
            return value
        import matplotlib.colors as mc

        if k is not None:    # darker for K < 5, lighter for K > 5
            mix = -0.7 * (5 - int(k)) / 5 if int(k) < 5 else min(0.7, (int(k) - 5) / 10)
        else:
            pairs = sorted({p for p in map(ta_pair, among) if p} | {pair})
            mix = (-0.55 + 1.1 * pairs.index(pair) / (len(pairs) - 1) if len(pairs) > 1
                   else float(np.clip(0.6 * np.log2(sum(pair) / 85), -0.6, 0.6)))
        rgb = mc.to_rgb(value)
        if mix < 0:
            return tuple(c * (1 + mix) for c in rgb)
        return tuple(c + (1 - c) * mix for c in rgb)

    def __init__(self, values: dict, shade: bool):
        super().__init__(values)
        self.shade = shade


COLORS = _Shades({"sdp": "tab:red", "dp": "tab:blue", "pddp": "tab:green", "pddp_s": "tab:purple", "to": "black"}, True)
MARKERS = _Shades({"sdp": "o", "dp": "s", "pddp": "^", "pddp_s": "v"}, False)
CURVE_STYLES = {"policy": "-", "refined": "--", "ArgminCost": ":"}


def method_order(method) -> tuple:
    """Sort key of a method or variant (:class:`~sdp_cli.report.rows.Variant`), numbers numerically: ``sdp-K2``
    before ``sdp-K10``, ``sdp-h32-ta16`` before ``sdp-h64-ta16`` before ``sdp-h64-ta63``."""
    v = as_variant(method)
    return v.method, (() if v.k is None else (int(v.k),)) + (tuple(v.pair) if v.pair else ())


def by_method(tab: pd.DataFrame, then: list[str]) -> pd.DataFrame:
    """``tab`` sorted by :func:`method_order`, then by the columns ``then``."""
    return tab.iloc[sorted(range(len(tab)), key=lambda i: (method_order(tab.method.iloc[i]), *tab[then].iloc[i]))]


def log_ticks(axis, lo: float, hi: float) -> None:
    """Readable ticks on a log axis (``ax.xaxis`` or ``ax.yaxis``): 1, 2, 5, 10, 20, ... (finer over about a decade) as plain
    numbers, no minor labels."""
    from matplotlib.ticker import FixedLocator, NullFormatter, StrMethodFormatter

    ticks = [m * 10 ** e for e in range(-4, 7) for m in (1, 2, 5) if lo <= m * 10 ** e <= hi]
    if len(ticks) < 4:   # about a decade: finer steps, so that the lower values can be read
        ticks = [m * 10 ** e for e in range(-4, 7) for m in (1, 1.5, 2, 3, 4, 5, 7) if lo <= m * 10 ** e <= hi]
    axis.set_major_locator(FixedLocator(ticks))
    axis.set_major_formatter(StrMethodFormatter("{x:g}"))
    axis.set_minor_formatter(NullFormatter())


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_fig(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    pyplot().close(fig)
    return atomic_write_bytes(path, lambda f: f.write(buf.getvalue()))


def save_csv(df: pd.DataFrame, path: Path) -> Path:
    """CSV; a ``ci95`` column reads "n/a" where there is no interval (one seed: see ``n_seeds``)."""
    for col in [c for c in df.columns if c.endswith("ci95")]:
        df = df.assign(**{col: [("n/a" if pd.isna(h) else h) for h in df[col]]})
    return atomic_write_bytes(path, lambda f: f.write(df.to_csv(index=False).encode()))


def save_md(df: pd.DataFrame, path: Path, title: str) -> Path:
    def fmt(v):
        return f"{v:.4g}" if isinstance(v, (float, np.floating)) else str(v)

    lines = [f"# {title}", "", "| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return atomic_write_bytes(path, lambda f: f.write(("\n".join(lines) + "\n").encode()))

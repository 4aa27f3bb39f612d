"""Gather the evaluation rows of every run under a folder into one tidy table.

Both layouts are read: DVC experiments (``runs/<exp>/<run>/it<k>/eval/e<E>-ta<T>/eval.csv``)
and ``sdp loop`` folders (``<out>/it<k>/eval/eval.csv``). Each row gets ``source`` (the CSV's
folder, where the rollout/refined artifacts lie), ``run`` and ``iteration`` when the CSV
did not carry them as tags.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.errors import SdpError
from sdp_cli.evaluate import read_evaluation

#: name of an iteration folder of a loop run, ``it<k>``
ITERATION_DIR = re.compile(r"^it(\d+)$")


def _run_and_iteration(csv: Path, root: Path) -> tuple[str, int | None]:
    parts = csv.relative_to(root).parts
    for i, p in enumerate(parts):
        m = ITERATION_DIR.match(p)
        if m:
            return "/".join(parts[:i]) or root.name, int(m.group(1))
    return "/".join(parts[:-1]) or root.name, None


def load_runs(root: str | Path) -> pd.DataFrame:
    """All ``eval.csv`` rows under ``root`` (``SdpError`` if there are none)."""
    root = Path(root)
    if not root.is_dir():
        raise SdpError(f"runs folder not found: {root}")
    frames = []
    for csv in sorted(root.rglob("eval.csv")):
        try:
            df = read_evaluation(csv)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
            raise SdpError(f"corrupt evaluation file {csv}: {e}") from None
        run, it = _run_and_iteration(csv, root)
        df["source"] = str(csv.parent)
        if "run" not in df:
            df["run"] = run
        if "iteration" not in df or df["iteration"].isna().all():
            df["iteration"] = it if it is not None else 0
        frames.append(df)
    if not frames:
        raise SdpError(f"no evaluation results (eval.csv) under {root}; run `sdp loop` or `dvc repro` first")
    df = pd.concat(frames, ignore_index=True)
    df["iteration"] = df["iteration"].astype(int)
    if "train_seed" in df:
        df["train_seed"] = df["train_seed"].fillna(0).astype(int)
    return df


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


def run_revisions(df: pd.DataFrame) -> pd.DataFrame:
    """The code revision that wrote each evaluation's rollouts: ``(task, method, iteration, git_rev)``
    rows, from the artifacts' provenance (a resumed loop may span several commits)."""
    from sdp_cli.data.artifacts import load_npz

    rows = []
    for r in df.drop_duplicates("source").itertuples():
        files = sorted(Path(r.source).glob("rollout*.npz"))
        if files:
            _, meta = load_npz(files[0], kind="rollout")
            rows.append({"task": r.task, "method": r.method, "iteration": int(r.iteration),
                         "git_rev": (meta.get("provenance") or {}).get("git_rev", "unknown")})
    return pd.DataFrame(rows, columns=["task", "method", "iteration", "git_rev"])

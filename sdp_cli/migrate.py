"""Evaluations written by older code, brought to this code's layout once: ``sdp migrate RUNS``.

An evaluation is an ``eval.csv`` with its manifest (:func:`sdp_cli.algorithm.evaluate.write_evaluation`). This code writes
manifest format :data:`LAYOUT`, whose rows carry every column the report reads; ``sdp report`` refuses older
ones in one line and names this command, instead of patching them up on every read. Format 1 rows may lack, and
the migration computes from the artifacts their manifest names:

- ``policy_wins`` / ``policy_ties``: a shared optimum used to count as a policy win; recounted from the refine
  (``inst_winner``, the per-instance costs), NaN where the refine is gone;
- the per-group violation rates (``controls_violation_rate``, ``obstacles_violation_rate``, ...) and
  ``terminal_cost_mean``, from the rollouts;
- a loop's ``n_algo``, from its ``loop_config.json`` (``<run>/it<k>/eval/``: the evaluation's folder);
- each manifest entry's ``git_rev``: the manifest's, where the entry has none.

The rows' other values, their order and the timing sidecar are kept; the files as they were stay beside them
(``eval.csv.v1``, ``eval.manifest.json.v1``), so nothing is lost. Migrating twice changes nothing.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.algorithm.argmin import policy_outcomes
from sdp_cli.data.artifacts import atomic_write_bytes, load_npz
from sdp_cli.errors import SdpError
from sdp_cli.algorithm.evaluate import (ARTIFACT_KEYS, LAYOUT, find_manifests, group_violation_rates, read_manifest,
                              terminal_cost_mean)

__all__ = ["LAYOUT", "outdated", "migrate_rows", "migrate_evaluation", "migrate_runs"]


def outdated(man: dict) -> bool:
    """Whether a manifest (as read) is of an older layout than this code's."""
    return int(man.get("format_version", 1)) < LAYOUT


def _fill(df: pd.DataFrame, marker: str, path_col: str, compute, stale: tuple[str, ...] = ()) -> pd.DataFrame:
    """Rows without a ``marker`` value get the columns ``compute(path)`` returns from the artifact named in
    ``path_col``; their ``stale`` columns, computed differently then, become NaN first (and stay NaN where the
    artifact is gone)."""
    old = df[marker].isna() if marker in df else pd.Series(True, index=df.index)
    if not old.any():
        return df
    df = df.copy()
    for col in (c for c in stale if c in df):
        df[col] = df[col].astype(float).where(~old)
    for i in df.index[old]:
        path = df.at[i, path_col] if path_col in df else None
        if isinstance(path, str) and Path(path).is_file():
            for col, v in compute(path).items():
                if col not in df:
                    df[col] = np.nan
                df.at[i, col] = v
    return df


def _policy_outcomes(refined: str) -> dict:
    with np.load(refined) as d:   # only the four per-instance arrays, not the trajectories
        wins, ties = policy_outcomes(d["inst_winner"], d["inst_pol_cost"], d["inst_base_cost"], d["inst_base_converged"])
    return {"policy_wins": wins, "policy_ties": ties}


def _violation_groups(rollouts: str) -> dict:
    return group_violation_rates(*load_npz(rollouts, kind="rollout"))


def _terminal_cost(rollouts: str) -> dict:
    return terminal_cost_mean(*load_npz(rollouts, kind="rollout"))


def _loop_n_algo(df: pd.DataFrame, folder: Path) -> pd.DataFrame:
    """``n_algo`` of the rows of a loop's evaluation in ``folder`` (``<run>/it<k>/eval/``) that lack it."""
    if "n_algo" in df and df.n_algo.notna().all():
        return df
    up = folder.parents
    cfg = up[1] / "loop_config.json" if len(up) > 1 else None
    if cfg is None or not cfg.is_file():
        return df
    try:
        n_algo = float(json.loads(cfg.read_text())["n_algo"])
    except (ValueError, KeyError, TypeError) as e:
        raise SdpError(f"corrupt loop config {cfg}: {e}") from None
    df = df.copy()
    df["n_algo"] = df["n_algo"].fillna(n_algo) if "n_algo" in df else n_algo
    return df


def migrate_rows(df: pd.DataFrame, folder: Path | None = None) -> pd.DataFrame:
    """The rows of a format-1 evaluation (with their artifacts' absolute paths in ``refined`` / ``rollouts``)
    with the columns this code computes (see the module docstring); ``folder``: the evaluation's, for a loop's
    ``n_algo``."""
    if "policy_wins" in df:
        df = _fill(df, "policy_ties", "refined", _policy_outcomes, stale=("policy_wins", "policy_ties"))
    df = _fill(df, "controls_violation_rate", "rollouts", _violation_groups)
    df = _fill(df, "terminal_cost_mean", "rollouts", _terminal_cost)
    return df if folder is None else _loop_n_algo(df, folder)


def migrate_evaluation(manifest: Path) -> bool:
    """Bring one evaluation (its manifest's path) to this code's layout; False if it already is."""
    man = read_manifest(manifest)
    if not outdated(man):
        return False
    csv = Path(man["eval"])
    try:
        df = pd.read_csv(csv)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise SdpError(f"corrupt evaluation file {csv} (named by {manifest}): {e}") from None
    entries = man["entries"]
    if len(entries) != len(df):
        raise SdpError(f"{manifest} describes {len(entries)} rows but {csv} has {len(df)}")
    paths = pd.DataFrame({k: [e.get(k) for e in entries] for k in ARTIFACT_KEYS}, index=df.index)
    new = migrate_rows(pd.concat([df, paths[[k for k in ARTIFACT_KEYS if k not in df]]], axis=1), csv.parent)
    new = new[[c for c in new.columns if c not in paths or c in df]]
    raw = json.loads(Path(manifest).read_text())   # its relative paths, as written
    for e in raw["entries"]:
        e["git_rev"] = e.get("git_rev") or raw.get("git_rev", "unknown")
    raw["format_version"] = LAYOUT
    for p in (csv, Path(manifest)):
        backup = p.with_name(p.name + ".v1")
        if not backup.exists():
            shutil.copy2(p, backup)
    if not new.equals(df):
        atomic_write_bytes(csv, lambda f: f.write(new.to_csv(index=False).encode()))
    text = json.dumps(raw, indent=1).encode()
    atomic_write_bytes(manifest, lambda f: f.write(text))
    return True


def migrate_runs(root: str | Path, log=lambda s: None) -> tuple[int, int]:
    """Migrate every evaluation under ``root``; ``(migrated, already current)``."""
    root = Path(root)
    if not root.is_dir():
        raise SdpError(f"runs folder not found: {root}" + (" (it is a file)" if root.exists() else ""))
    done = current = 0
    for path in find_manifests(root):
        if migrate_evaluation(path):
            done += 1
            log(f"migrated {path.parent}")
        else:
            current += 1
    return done, current

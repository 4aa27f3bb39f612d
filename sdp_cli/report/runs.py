"""Gather the evaluation rows of every run under a folder into one tidy table.

Evaluations are found through their manifests (``*.manifest.json``, written next to each
``eval.csv`` by ``sdp evaluate`` and ``sdp loop``; :mod:`sdp_cli.evaluate`), whatever the
folder layout: a DVC experiment or ``sdp loop`` folders. Each row gets, from its manifest,
``run``, ``iteration``, ``git_rev`` and the absolute paths of the files it comes from
(``rollouts``, ``refined``, ``policy``, ``data``), plus ``source`` (the manifest's folder);
the report opens only those files. An ``eval.csv`` without a manifest is not read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.argmin import policy_outcomes
from sdp_cli.data.artifacts import load_npz
from sdp_cli.errors import SdpError
from sdp_cli.evaluate import (ARTIFACT_KEYS, MANIFEST_SUFFIX, group_violation_rates, read_evaluation,
                               read_manifest, terminal_cost_mean)

#: columns load_runs adds that hold paths on this machine (never written to committed tables)
PATH_COLUMNS = ("source", *ARTIFACT_KEYS)


def load_runs(root: str | Path, log=lambda s: None, allow_empty: bool = False) -> pd.DataFrame | None:
    """All evaluation rows under ``root`` that a manifest names (``SdpError`` if there are none, or None
    with ``allow_empty``)."""
    root = Path(root)
    if not root.is_dir():
        raise SdpError(f"runs folder not found: {root}")
    frames = []
    for path in sorted(root.rglob("*" + MANIFEST_SUFFIX)):
        man = read_manifest(path)
        try:
            df = read_evaluation(man["eval"])
        except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
            raise SdpError(f"corrupt evaluation file {man['eval']} (named by {path}): {e}") from None
        entries = man["entries"]
        if len(entries) != len(df):
            raise SdpError(f"{path} describes {len(entries)} rows but {man['eval']} has {len(df)}")
        for k in ("run", "iteration", *ARTIFACT_KEYS):
            df[k] = [e.get(k) for e in entries]
        # the code that computed each row (from its artifacts); older manifests: the manifest's
        df["git_rev"] = [e.get("git_rev") or man.get("git_rev", "unknown") for e in entries]
        df["run"] = df["run"].where(df["run"].notna(), path.parent.name)
        df["iteration"] = df["iteration"].fillna(0).astype(int)
        df["source"] = str(path.parent)
        frames.append(df)
    unnamed = sum(1 for _ in root.rglob("eval.csv")) - len(frames)
    if unnamed > 0:
        log(f"ignoring {unnamed} eval.csv file(s) under {root} without a manifest (written before manifests "
            "existed, or not by sdp): re-run their evaluation to include them")
    if not frames:
        if allow_empty:
            return None
        raise SdpError(f"no evaluation results (eval.csv with its manifest) under {root}; run `sdp loop` or "
                       "`dvc repro` first")
    df = _backfill_older_rows(pd.concat(frames, ignore_index=True))
    if "train_seed" in df:
        df["train_seed"] = df["train_seed"].fillna(0).astype(int)
    return df


def _backfill(df: pd.DataFrame, marker: str, path_col: str, compute, stale: tuple[str, ...] = ()) -> pd.DataFrame:
    """Rows evaluated by older code (no ``marker`` value) get the columns ``compute(path)`` returns from the
    artifact named in ``path_col``; their ``stale`` columns, computed differently then, become NaN first
    (and stay NaN where the artifact is gone)."""
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


def _loop_n_algo(df: pd.DataFrame) -> pd.DataFrame:
    """``n_algo`` of loop rows evaluated before loops recorded it, from the run's ``loop_config.json``
    (``<run>/it<k>/eval/`` is the evaluation's folder), read once per evaluation; NaN for rows of no loop."""
    if "source" not in df or ("n_algo" in df and df.n_algo.notna().all()):
        return df
    df = df.copy()
    if "n_algo" not in df:
        df["n_algo"] = np.nan
    for source, idx in df[df.n_algo.isna()].groupby("source").groups.items():
        up = Path(str(source)).parents
        cfg = up[1] / "loop_config.json" if len(up) > 1 else None
        if cfg is not None and cfg.is_file():
            try:
                df.loc[idx, "n_algo"] = float(json.loads(cfg.read_text())["n_algo"])
            except (ValueError, KeyError, TypeError) as e:
                raise SdpError(f"corrupt loop config {cfg}: {e}") from None
    return df


def _backfill_older_rows(df: pd.DataFrame) -> pd.DataFrame:
    """Columns that older evaluations lack or computed differently, from the artifacts they name:
    ``policy_wins`` / ``policy_ties`` (ties used to count as wins) from the refine, the per-group
    violation rates (``obstacles_violation_rate``, ...) and ``terminal_cost_mean`` from the rollouts, a loop's
    ``n_algo`` from its config."""
    if "policy_wins" in df:
        df = _backfill(df, "policy_ties", "refined", _policy_outcomes, stale=("policy_wins", "policy_ties"))
    df = _backfill(df, "controls_violation_rate", "rollouts", _violation_groups)
    return _loop_n_algo(_backfill(df, "terminal_cost_mean", "rollouts", _terminal_cost))


def run_revisions(df: pd.DataFrame) -> pd.DataFrame:
    """The code revision of each evaluation (from its manifest): ``(task, method, train_seed, iteration,
    git_rev)`` rows (a resumed loop may span several commits; seeds may be run by different ones)."""
    cols = ["task", "method", "train_seed", "iteration", "git_rev"]
    return df[cols].drop_duplicates().reset_index(drop=True) if len(df) else pd.DataFrame(columns=cols)

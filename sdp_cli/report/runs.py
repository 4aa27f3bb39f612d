"""Gather the evaluation rows of every run under a folder into one tidy table.

Evaluations are found through their manifests (``*.manifest.json``, written next to each
``eval.csv`` by ``sdp evaluate`` and ``sdp loop``; :mod:`sdp_cli.evaluate`), whatever the
folder layout: a DVC experiment or ``sdp loop`` folders. Each row gets, from its manifest,
``run``, ``iteration``, ``git_rev`` and the absolute paths of the files it comes from
(``rollouts``, ``refined``, ``policy``, ``data``), plus ``source`` (the manifest's folder);
the report opens only those files. An ``eval.csv`` without a manifest is not read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sdp_cli.argmin import policy_outcomes
from sdp_cli.data.artifacts import load_npz
from sdp_cli.errors import SdpError
from sdp_cli.evaluate import (ARTIFACT_KEYS, MANIFEST_SUFFIX, group_violation_rates, read_evaluation,
                               read_manifest)

#: columns load_runs adds that hold paths on this machine (never written to committed tables)
PATH_COLUMNS = ("source", *ARTIFACT_KEYS)


def load_runs(root: str | Path, log=lambda s: None) -> pd.DataFrame:
    """All evaluation rows under ``root`` that a manifest names (``SdpError`` if there are none)."""
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
        raise SdpError(f"no evaluation results (eval.csv with its manifest) under {root}; run `sdp loop` or "
                       "`dvc repro` first")
    df = _add_violation_groups(_recount_policy_wins(pd.concat(frames, ignore_index=True)))
    if "train_seed" in df:
        df["train_seed"] = df["train_seed"].fillna(0).astype(int)
    return df


def _recount_policy_wins(df: pd.DataFrame) -> pd.DataFrame:
    """Rows evaluated before ``policy_ties`` existed counted a shared optimum as a policy win: recount
    ``policy_wins`` and ``policy_ties`` from their refine artifacts (rows without one get NaN)."""
    if "policy_wins" not in df:
        return df
    old = df["policy_ties"].isna() if "policy_ties" in df else pd.Series(True, index=df.index)
    if not old.any():
        return df
    df = df.copy()
    if "policy_ties" not in df:
        df["policy_ties"] = np.nan
    df["policy_wins"] = df["policy_wins"].astype(float)
    for i in df.index[old]:
        refined = df.at[i, "refined"] if "refined" in df else None
        if not isinstance(refined, str) or not Path(refined).is_file():
            df.loc[i, ["policy_wins", "policy_ties"]] = np.nan
            continue
        with np.load(refined) as d:
            df.loc[i, ["policy_wins", "policy_ties"]] = policy_outcomes(
                d["inst_winner"], d["inst_pol_cost"], d["inst_base_cost"], d["inst_base_converged"])
    return df


def _add_violation_groups(df: pd.DataFrame) -> pd.DataFrame:
    """Rows evaluated before the per-group violation rates existed (``obstacles_violation_rate``, ...) get
    them from their rollout artifacts (:func:`sdp_cli.evaluate.group_violation_rates`)."""
    old = df["controls_violation_rate"].isna() if "controls_violation_rate" in df else pd.Series(True, index=df.index)
    todo = [i for i in df.index[old] if isinstance(df.at[i, "rollouts"], str) and Path(df.at[i, "rollouts"]).is_file()]
    if not todo:
        return df
    df = df.copy()
    for i in todo:
        r, meta = load_npz(df.at[i, "rollouts"], kind="rollout")
        for col, v in group_violation_rates(r, meta).items():
            if col not in df:
                df[col] = np.nan
            df.at[i, col] = v
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
    """The code revision of each evaluation (from its manifest): ``(task, method, iteration, git_rev)``
    rows (a resumed loop may span several commits)."""
    cols = ["task", "method", "iteration", "git_rev"]
    return df[cols].drop_duplicates().reset_index(drop=True) if len(df) else pd.DataFrame(columns=cols)

"""Gather the evaluation rows of every run under a folder into one tidy table.

Evaluations are found through their manifests (``*.manifest.json``, written next to each
``eval.csv`` by ``sdp evaluate`` and ``sdp loop``; :mod:`sdp_cli.algorithm.evaluate`), whatever the
folder layout: a DVC experiment or ``sdp loop`` folders, symlinked folders followed. Each row
gets, from its manifest, ``run``, ``iteration``, ``git_rev`` and the absolute paths of the files it comes from
(``rollouts``, ``refined``, ``policy``, ``data``), plus ``source`` (the manifest's folder);
the report opens only those files. An ``eval.csv`` without a manifest is not read; evaluations written by
older code are refused in one line naming ``sdp migrate`` (:mod:`sdp_cli.migrate`), which brings them up to
date once.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from sdp_cli.errors import SdpError
from sdp_cli.algorithm.evaluate import ARTIFACT_KEYS, MANIFEST_SUFFIX, files_named, read_evaluation, read_manifest
from sdp_cli.migrate import outdated

#: columns load_runs adds that hold paths on this machine (never written to committed tables)
PATH_COLUMNS = ("source", *ARTIFACT_KEYS)


def load_runs(root: str | Path, log=lambda s: None, allow_empty: bool = False) -> pd.DataFrame | None:
    """All evaluation rows under ``root`` that a manifest names (``SdpError`` if there are none, or None
    with ``allow_empty``)."""
    root = Path(root)
    if not root.is_dir():
        raise SdpError(f"runs folder not found: {root}")
    found = files_named(root, lambda name: name.endswith(MANIFEST_SUFFIX) or name == "eval.csv")   # one walk
    frames, old = [], []
    for path in (p for p in found if p.name.endswith(MANIFEST_SUFFIX)):
        man = read_manifest(path)
        if outdated(man):
            old.append(path.parent)
            continue
        try:
            df = read_evaluation(man["eval"])
        except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
            raise SdpError(f"corrupt evaluation file {man['eval']} (named by {path}): {e}") from None
        entries = man["entries"]
        if len(entries) != len(df):
            raise SdpError(f"{path} describes {len(entries)} rows but {man['eval']} has {len(df)}")
        for k in ("run", "iteration", *ARTIFACT_KEYS):
            df[k] = [e.get(k) for e in entries]
        df["git_rev"] = [e["git_rev"] for e in entries]   # the code that computed each row (from its artifacts)
        df["run"] = df["run"].where(df["run"].notna(), path.parent.name)
        df["iteration"] = df["iteration"].fillna(0).astype(int)
        df["source"] = str(path.parent)
        frames.append(df)
    if old:
        raise SdpError(f"{len(old)} evaluation(s) under {root} were written by older code (e.g. {old[0]}); "
                       f"bring them up to date once with `sdp migrate {root}`")
    unnamed = sum(p.name == "eval.csv" for p in found) - len(frames)
    if unnamed > 0:
        log(f"ignoring {unnamed} eval.csv file(s) under {root} without a manifest (written before manifests "
            "existed, or not by sdp): re-run their evaluation to include them")
    if not frames:
        if allow_empty:
            return None
        raise SdpError(f"no evaluation results (eval.csv with its manifest) under {root}; run `sdp loop` or "
                       "`dvc repro` first")
    df = pd.concat(frames, ignore_index=True)
    if "train_seed" in df:
        df["train_seed"] = df["train_seed"].fillna(0).astype(int)
    return df


def run_revisions(df: pd.DataFrame) -> pd.DataFrame:
    """The code revision of each evaluation (from its manifest): ``(task, method, train_seed, iteration,
    git_rev)`` rows (a resumed loop may span several commits; seeds may be run by different ones), and its
    ``results_version`` (:data:`sdp_cli.RESULTS_VERSION`, recorded by loops since version 4) where the rows
    have one."""
    cols = ["task", "method", "train_seed", "iteration", "git_rev"]
    if "results_version" in df and df.results_version.notna().any():
        cols.append("results_version")
    return df[cols].drop_duplicates().reset_index(drop=True) if len(df) else pd.DataFrame(columns=cols)

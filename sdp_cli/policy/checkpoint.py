"""Policy checkpoints: one ``torch.save`` file, written atomically.

Content (a dict of plain types and tensors, loadable with ``weights_only=True``):
``format``, ``format_version``, ``method``, ``config`` (full :class:`TrainConfig`, nested by section),
``dims`` (n_action, n_obs, n_xi, ndx), ``action``, ``task``, ``task_options``, ``task_params``,
``dataset`` (path, sha256 fingerprint, n_traj, T), ``provenance`` (versions, git revision, CPU model,
torch thread count, CUDA device), ``device``,
``epoch``, ``step``, ``total_steps``, ``finished``, ``model`` (weights + normalizer buffers),
``ema_model`` (same keys, EMA weights) and ``train_state`` (optimizer, LR schedule, EMA
internals, RNG state) for ``--resume``. No clock readings (same seed, same bytes): the
training wall time is in the run folder's timing sidecar (see :mod:`sdp_cli.training.train`).

Format versions: 2 stores ``config`` as :meth:`TrainConfig.to_dict` (sections ``policy``, ``data``, ``optim``,
``sobolev``); 1 stored one flat dict with older names (``T_h``, ``K``, ``alpha_sobolev``, ...).
:func:`load_checkpoint` migrates version 1 on reading (:func:`migrate`), so runs started before resume.
"""

from __future__ import annotations

import io
from pathlib import Path
import sys

import torch

from sdp_cli.data.artifacts import atomic_write_bytes, file_sha256, runtime_provenance  # noqa: F401 (re-export)
from sdp_cli.errors import SdpError
from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.registry import make_policy

FORMAT = "sdp-policy"
FORMAT_VERSION = 2
CHECKPOINT_NAME = "checkpoint.pt"


def canonical(obj):
    """``obj`` with every tensor a fresh contiguous copy, every container rebuilt and every string interned:
    pickle memoizes objects by identity, so equal state must be equal object graphs to give equal bytes (a
    resumed optimizer's ``"step"`` keys were strings of their own where a fresh one's were the same object
    as the checkpoint's ``"step"`` key, and the checkpoints of equal runs differed)."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().clone().contiguous()
    if isinstance(obj, str):
        return sys.intern(obj)
    if isinstance(obj, dict):
        return {canonical(k): canonical(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(canonical(v) for v in obj)
    return obj


def save_checkpoint(path: str | Path, payload: dict) -> Path:
    """Atomically write ``payload`` (adds format, version, provenance), canonically (:func:`canonical`)."""
    payload = canonical({"format": FORMAT, "format_version": FORMAT_VERSION, "provenance": runtime_provenance(),
                         **payload})
    buf = io.BytesIO()
    torch.save(payload, buf)
    return atomic_write_bytes(path, lambda f: f.write(buf.getvalue()))


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run folder holding ``checkpoint.pt``."""
    p = Path(path)
    if p.is_dir():
        p = p / CHECKPOINT_NAME
    if not p.is_file():
        raise SdpError(f"checkpoint not found: {path}")
    return p


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    p = resolve_checkpoint(path)
    try:
        ck = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a corrupt file for the user
        # torch's own text advises weights_only=False (unsafe): never pass that on
        raise SdpError(f"corrupt checkpoint {p}: expected an sdp policy checkpoint written by `sdp train` "
                       f"({type(e).__name__})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise SdpError(f"{p} is not an sdp policy checkpoint")
    if ck.get("format_version", 0) > FORMAT_VERSION:
        raise SdpError(f"{p} has format_version {ck['format_version']}, newer than this sdp; upgrade sdp")
    check_finite(ck, p)
    return migrate(ck)


def check_finite(ck: dict, path) -> None:
    """``SdpError`` if the checkpoint's weights or EMA weights hold NaN or infinity: such a policy cannot act,
    and its rollouts would be reported as a result (every one diverged)."""
    for key in ("model", "ema_model"):
        sd = ck.get(key)
        if not isinstance(sd, dict):
            continue
        bad = total = 0
        for v in sd.values():
            if isinstance(v, torch.Tensor) and v.is_floating_point():
                bad += int((~torch.isfinite(v)).sum())
                total += v.numel()
        if bad:
            raise SdpError(f"{path}: {bad} of {total} {'EMA ' if key == 'ema_model' else ''}weights are not "
                           f"finite (NaN or infinity); this checkpoint cannot act")


def migrate(ck: dict) -> dict:
    """A checkpoint of an older format version as the current version reads it (in memory; the file stays)."""
    if ck.get("format_version", 1) < 2:
        ck = {**ck, "config": TrainConfig.from_dict(ck["config"]).to_dict(), "format_version": FORMAT_VERSION}
    return ck


def policy_from_checkpoint(ck: dict, use_ema: bool = True):
    """The checkpoint's policy object (:func:`~sdp_cli.policy.registry.make_policy`) with its EMA weights
    (``use_ema``, when saved) or its raw ones; not bound to a task (:meth:`Policy.bind`)."""
    policy = make_policy(TrainConfig.from_dict(ck["config"]), ck["dims"])
    policy.load_state_dict(ck["ema_model"] if use_ema and ck.get("ema_model") is not None else ck["model"])
    return policy

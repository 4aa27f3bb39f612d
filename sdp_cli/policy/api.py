"""``load_policy``: a trained policy, bound to its task, as used at rollout time (see :mod:`sdp_cli.policy`)."""

from __future__ import annotations

from sdp_cli.data.artifacts import resolve_recorded
from sdp_cli.policy.base import Policy
from sdp_cli.policy.checkpoint import load_checkpoint, policy_from_checkpoint, resolve_checkpoint


def load_policy(path, device="cpu", use_ema: bool = True) -> Policy:
    """Load a trained policy from a checkpoint file or a run folder (``checkpoint.pt``): the method's
    policy class (from the registry) with the EMA weights (or the raw ones), its task attached and checked
    against the checkpoint's recorded task identity, in eval mode on ``device``."""
    path = resolve_checkpoint(path)
    ck = load_checkpoint(path, map_location=device)
    policy = policy_from_checkpoint(ck, use_ema).bind(ck, device)
    if policy.dataset_info.get("path"):   # recorded relative to the checkpoint's folder
        policy.dataset_info["path"] = str(resolve_recorded(policy.dataset_info["path"], path.parent))
    return policy

"""Normalization fitted on a dataset, saved with the weights (an ``nn.Module`` of buffers).

Every quantity the networks see is mapped to about ``[-1, 1]`` by min-max scaling,
``y_n = (y - center) / scale`` with ``center`` the mid-range and ``scale`` the half-range
(``scale = 1`` on constant coordinates), as diffusion policy does. This matters because
diffusers' ``DDPMScheduler(clip_sample=True)`` clips the predicted ``tau_0`` to [-1, 1].

- ``action`` (A,): the diffused action ``a_t`` (``u`` for torque control, ``g(x)`` otherwise);
  for the MLP baselines, the control ``u``;
- ``obs`` (n_o,): one observation ``o_t = (obs(x_t), u_{t-1})``;
- ``xi`` (n_xi,): task parameters;
- ``x`` (ndx,): the state tangent. Derivatives are taken w.r.t. a *normalized* tangent
  perturbation ``delta``, ``x = x_t (+) (x_scale * delta)``.

Jacobians follow the chain rule: ``d a_n / d delta = diag(1/a_scale) (d a / d dx) diag(x_scale)``
(:meth:`Normalizer.action_jacobian`), and likewise for observations.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

_KINDS = ("action", "obs", "xi", "x")


def _center_scale(values: np.ndarray, min_range: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(values, dtype=np.float64).reshape(-1, values.shape[-1])
    lo, hi = v.min(0), v.max(0)
    scale = (hi - lo) / 2
    center = (hi + lo) / 2
    scale = np.where(scale > min_range, scale, 1.0)
    return center, scale


class Normalizer(nn.Module):
    """Buffers ``<kind>_center``, ``<kind>_scale`` for kind in action, obs, xi, x."""

    def __init__(self, n_action: int, n_obs: int, n_xi: int, ndx: int):
        super().__init__()
        for kind, n in zip(_KINDS, (n_action, n_obs, n_xi, ndx)):
            self.register_buffer(f"{kind}_center", torch.zeros(n))
            self.register_buffer(f"{kind}_scale", torch.ones(n))

    @classmethod
    def fit(cls, action: np.ndarray, obs: np.ndarray, xi: np.ndarray, x_tangent: np.ndarray) -> "Normalizer":
        """Fit on samples ``(..., A)``, ``(..., n_o)``, ``(..., n_xi)``, ``(..., ndx)``."""
        norm = cls(action.shape[-1], obs.shape[-1], xi.shape[-1], x_tangent.shape[-1])
        for kind, values in zip(_KINDS, (action, obs, xi, x_tangent)):
            c, s = _center_scale(values)
            getattr(norm, f"{kind}_center").copy_(torch.as_tensor(c))
            getattr(norm, f"{kind}_scale").copy_(torch.as_tensor(s))
        norm.x_center.zero_()  # the tangent has no meaningful origin: only its scale is used
        return norm

    def union(self, other: "Normalizer") -> "Normalizer":
        """A normalizer whose ranges cover both ``self``'s and ``other``'s (same sizes).

        The loop's warm start (``sdp train --init``) keeps the previous policy's normalizer
        only as far as it covers the new dataset: with ``clip_sample`` the policy cannot
        output actions outside its normalized [-1, 1], and policy-warm-started datasets are
        wider than iteration 0's. The state-tangent scale is the larger of the two.
        """
        out = Normalizer(*(getattr(self, f"{k}_center").numel() for k in _KINDS))
        for kind in _KINDS:
            c1, s1 = getattr(self, f"{kind}_center"), getattr(self, f"{kind}_scale")
            c2, s2 = getattr(other, f"{kind}_center"), getattr(other, f"{kind}_scale")
            if c1.shape != c2.shape:
                raise ValueError(f"normalizer sizes differ for {kind}: {tuple(c1.shape)} vs {tuple(c2.shape)}")
            lo, hi = torch.minimum(c1 - s1, c2 - s2), torch.maximum(c1 + s1, c2 + s2)
            getattr(out, f"{kind}_center").copy_((hi + lo) / 2)
            getattr(out, f"{kind}_scale").copy_((hi - lo) / 2)
        out.x_center.zero_()
        out.x_scale.copy_(torch.maximum(self.x_scale, other.x_scale))
        return out

    # ------------------------------------------------------------ values
    def normalize(self, kind: str, y: torch.Tensor) -> torch.Tensor:
        """``(y - center) / scale`` over the last axis."""
        return (y - getattr(self, f"{kind}_center")) / getattr(self, f"{kind}_scale")

    def unnormalize(self, kind: str, y: torch.Tensor) -> torch.Tensor:
        return y * getattr(self, f"{kind}_scale") + getattr(self, f"{kind}_center")

    # --------------------------------------------------------- Jacobians
    def jacobian(self, kind: str, J: torch.Tensor) -> torch.Tensor:
        """``d y_n / d delta`` from ``d y / d dx``: (..., n_kind, ndx) -> same shape."""
        return J * self.x_scale / getattr(self, f"{kind}_scale")[:, None]

    def action_jacobian(self, J: torch.Tensor) -> torch.Tensor:
        return self.jacobian("action", J)

    def obs_jacobian(self, J: torch.Tensor) -> torch.Tensor:
        return self.jacobian("obs", J)

    def tangent(self, delta: torch.Tensor) -> torch.Tensor:
        """Physical tangent ``dx = x_scale * delta`` of a normalized perturbation (..., ndx)."""
        return delta * self.x_scale

"""MLP baselines PDDP and PDDP+S: ``u = pi(obs(x), xi)`` trained by regression on the TO data.

PDDP uses the plain regression loss; PDDP+S adds the stochastic Sobolev term of eq. (4)
with the feedback gains ``K_t = du_t/dx_t`` as target Jacobians. The consensus penalty
of the original PDDP paper (which couples the policy back into the optimizer) is out of
scope here: the optimizer-side coupling is the alternating loop's warm start. Registered as ``pddp`` and
``pddp_s``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

import numpy as np

from sdp_cli.data.normalizer import Normalizer
from sdp_cli.losses.sobolev import sobolev_term
from sdp_cli.policy.base import Policy, as_tensor
if TYPE_CHECKING:   # annotations only: the config does not import the families at run time either
    from sdp_cli.policy.config import TrainConfig


class MLPPolicy(Policy):
    """``u (B, nu) = MLP(obs(x) (B, n_obs), xi (B, n_xi))`` (SiLU) on (state, control) pairs.

    ``forward(obs_n, xi_n) -> u_n``, normalized. The normalizer's ``obs`` entries cover ``(obs(x), u_prev)``;
    the MLP uses the first ``n_obs`` of them (no ``u_prev``). State dict: ``normalizer.*``, ``mlp.*``.
    Subclasses may replace :meth:`build_network` (the test suite's toy linear family does).
    """

    chunked = False

    def __init__(self, config: TrainConfig, dims: dict):
        super().__init__(config, dims)
        d = self.dims
        self.normalizer = Normalizer(d["n_action"], d["n_obs"] + d["n_action"], d["n_xi"], d["ndx"])
        self.build_network()

    def build_network(self) -> None:
        layers, d = [], self.dims["n_obs"] + self.dims["n_xi"]
        for h in self.config.policy.mlp_hidden:
            layers += [nn.Linear(d, h), nn.SiLU()]
            d = h
        layers.append(nn.Linear(d, self.dims["n_action"]))
        self.mlp = nn.Sequential(*layers)

    def forward(self, obs_n, xi_n):
        return self.mlp(torch.cat([obs_n, xi_n], dim=-1))

    @classmethod
    def make_dataset(cls, config, task, arrays, with_jacobians):
        from sdp_cli.data.chunks import PairDataset

        return PairDataset(task, arrays, with_jacobians=with_jacobians), cls.action_for(config, task)

    @classmethod
    def action_for(cls, config, task):
        return "u"   # the MLPs act on torques

    @classmethod
    def dims_for(cls, config, task, action):
        return {"n_action": task.nu, "n_obs": task.n_obs, "n_xi": task.n_xi, "ndx": task.ndx}

    def balance_terms(self, tensors):
        return tensors["u"], tensors["jac"]

    def compute_loss(self, batch: dict, generator: torch.Generator | None = None):
        """Eq. (4) (``pddp_s``) or plain regression (``pddp``): ``batch`` has ``obs, obs_jac, u, xi`` and ``jac``
        = K (normalized). The Sobolev term is multiplied by :attr:`sobolev_scale` and then by
        ``sobolev_alpha``; the ``sobolev`` part reported is the scaled term."""
        cfg = self.config.sobolev
        obs, obs_jac, u, xi = batch["obs"], batch["obs_jac"], batch["u"], batch["xi"]
        if not self.config.uses_sobolev:
            reg = ((self(obs, xi) - u) ** 2).mean()
            return reg, {"dp": reg.detach(), "sobolev": torch.zeros((), device=u.device)}

        def f(delta):
            return self(obs + torch.einsum("boi,bi->bo", obs_jac, delta), xi)

        J = batch["jac"]
        pred, term = sobolev_term(cfg.mode, f, J.shape[-1], J, cfg.n_proj, generator)
        reg = ((pred - u) ** 2).mean()
        sob = self.sobolev_scale * term.mean()
        return reg + cfg.weight * sob, {"dp": reg.detach(), "sobolev": sob.detach()}

    @torch.no_grad()
    def act(self, x, xi) -> np.ndarray:
        """``u (B, nu)`` from ``x (B, nx)`` and ``xi (B, n_xi)`` (physical units, not clipped)."""
        x = np.asarray(x, float)
        o = as_tensor(self.task.observation(x), self.device)
        n = o.shape[-1]
        o = (o - self.normalizer.obs_center[:n]) / self.normalizer.obs_scale[:n]
        u = self(o, self.normalizer.normalize("xi", as_tensor(xi, self.device)))
        return self.normalizer.unnormalize("action", u).double().cpu().numpy()

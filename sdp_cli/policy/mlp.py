"""MLP baselines PDDP and PDDP+S: ``u = pi(obs(x), xi)`` trained by regression on the TO data.

PDDP uses the plain regression loss; PDDP+S adds the stochastic Sobolev term of eq. (4)
with the feedback gains ``K_t = du_t/dx_t`` as target Jacobians. The consensus penalty
of the original PDDP paper (which couples the policy back into the optimizer) is out of
scope here: the optimizer-side coupling is the alternating loop's warm start.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from sdp_cli.data.normalizer import Normalizer
from sdp_cli.losses.sobolev import sobolev_term
if TYPE_CHECKING:   # annotations only: the config does not import the families at run time either
    from sdp_cli.policy.config import TrainConfig


class MLPNet(nn.Module):
    """Normalizer + MLP (SiLU). ``forward(obs_n (B, n_obs), xi_n (B, n_xi)) -> u_n (B, nu)``.

    The normalizer's ``obs`` entries cover ``(obs(x), u_prev)``; the MLP uses the first
    ``n_obs`` of them (no ``u_prev``).
    """

    def __init__(self, cfg: TrainConfig, nu: int, n_obs: int, n_xi: int, ndx: int):
        super().__init__()
        self.cfg = cfg
        self.dims = {"n_action": nu, "n_obs": n_obs, "n_xi": n_xi, "ndx": ndx}
        self.normalizer = Normalizer(nu, n_obs + nu, n_xi, ndx)
        layers, d = [], n_obs + n_xi
        for h in cfg.mlp_hidden:
            layers += [nn.Linear(d, h), nn.SiLU()]
            d = h
        layers.append(nn.Linear(d, nu))
        self.mlp = nn.Sequential(*layers)

    def forward(self, obs_n, xi_n):
        return self.mlp(torch.cat([obs_n, xi_n], dim=-1))


def mlp_loss(net: MLPNet, batch: dict, cfg: TrainConfig, generator: torch.Generator | None = None,
             sobolev: bool = False, sobolev_scale: float = 1.0):
    """Eq. (4) (or plain regression): ``batch`` has ``obs, obs_jac, u, xi`` and ``jac`` = K (normalized).
    The Sobolev term is multiplied by ``sobolev_scale`` (:func:`~sdp_cli.losses.sobolev.balance_scale`)
    and then by ``cfg.alpha_sobolev``; the ``sobolev`` part reported is the scaled term."""
    obs, obs_jac, u, xi = batch["obs"], batch["obs_jac"], batch["u"], batch["xi"]
    if not sobolev:
        reg = ((net(obs, xi) - u) ** 2).mean()
        return reg, {"dp": reg.detach(), "sobolev": torch.zeros((), device=u.device)}

    def f(delta):
        return net(obs + torch.einsum("boi,bi->bo", obs_jac, delta), xi)

    J = batch["jac"]
    pred, term = sobolev_term(cfg.sobolev_mode, f, J.shape[-1], J, cfg.n_proj, generator)
    reg = ((pred - u) ** 2).mean()
    sob = sobolev_scale * term.mean()
    return reg + cfg.sobolev_weight * sob, {"dp": reg.detach(), "sobolev": sob.detach()}

"""Methods: the registry that training, checkpoints, rollouts and the estimate dispatch through.

A *method* is a name, a *family* and whether it trains with the Sobolev term. The family says
how a method's data are cut into samples, its network is built, its loss is computed and its
trained policy is run (:class:`MethodFamily`). Built in (:mod:`sdp_cli.policy.families`):

- diffusion (chunked, Algorithm 2): ``sdp`` (Sobolev, eq. (6)) and ``dp`` (eq. (2));
- MLP (one control per state): ``pddp`` and ``pddp_s`` (Sobolev, eq. (4)),

registered when the package ``sdp_cli.policy`` is imported (which any import of this module does first).

Adding a method is one :class:`MethodFamily` subclass (or a new name for an existing family)
and one :func:`register_method` call; ``tests/test_method_registry.py`` adds a toy method that way
and trains, saves, loads and rolls it out through ``sdp``'s own code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from sdp_cli.errors import SdpError


class MethodFamily:
    """What a family of methods implements (shapes in the docstrings of the built-in families)."""

    #: plans chunks of T_h actions from (x, u_prev, xi) instead of one control per state: the trained
    #: policy is then a :class:`~sdp_cli.policy.api.DiffusionPolicy` (``predict_chunk``, Algorithm 2),
    #: else an :class:`~sdp_cli.policy.api.MLPPolicy` (``act``); rollouts and T_a options follow it
    chunked: bool = False

    def dims(self, cfg, task, action: str) -> dict:
        """Network sizes ``{n_action, n_obs, n_xi, ndx}``."""
        raise NotImplementedError

    def dataset(self, cfg, task, arrays: dict, with_jacobians: bool):
        """``(dataset, action)``: the training samples of a TO dataset (``.tensors(normalizer, device)``,
        ``.epoch_size()``) and the action variable the network predicts."""
        raise NotImplementedError

    def build_net(self, cfg, dims: dict):
        """A fresh ``nn.Module`` with a ``normalizer`` attribute."""
        raise NotImplementedError

    def scheduler(self, cfg):
        """The noise scheduler the loss and sampling use, or None."""
        return None

    def loss(self, cfg, scheduler, sobolev: bool, sobolev_scale: float) -> Callable:
        """``loss_fn(net, batch, generator) -> (loss, {"dp": regression, "sobolev": term})``."""
        raise NotImplementedError

    def balance_terms(self, cfg, tensors: dict):
        """``(targets, jacobians)`` of the Sobolev balance (:func:`sdp_cli.losses.sobolev.balance_scale`)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Method:
    name: str
    family: MethodFamily
    sobolev: bool
    description: str = ""


_REGISTRY: dict[str, Method] = {}


def register_method(name: str, family: MethodFamily, sobolev: bool, description: str = "") -> Method:
    """Make ``name`` a method (``sdp train --method name``); re-registering replaces it."""
    if not name or not name.replace("_", "").isalnum():
        raise SdpError(f"method names are identifiers, got {name!r}")
    m = Method(name, family, bool(sobolev), description)
    _REGISTRY[name] = m
    return m


def get_method(name: str) -> Method:
    if name not in _REGISTRY:
        raise SdpError(f"method must be one of {', '.join(_REGISTRY)}; got {name!r}")
    return _REGISTRY[name]


def method_names() -> tuple[str, ...]:
    return tuple(_REGISTRY)

"""Methods: the registry that training, checkpoints, rollouts and the estimate dispatch through.

A *method* is a name, a policy class (a :class:`~sdp_cli.policy.base.Policy` subclass: its family) and
whether it trains with the Sobolev term. Built in:

- ``sdp`` (Sobolev, eq. (6)) and ``dp`` (eq. (2)): :class:`sdp_cli.policy.diffusion.DiffusionUnetPolicy`
  (chunked, Algorithm 2);
- ``pddp`` and ``pddp_s`` (Sobolev, eq. (4)): :class:`sdp_cli.policy.mlp.MLPPolicy` (one control per state).

The built-in classes are named as ``"module:Class"`` strings and imported when a policy is built, so reading
the registry (the CLI's start-up, option checks) does not import torch. Adding a family is one module with a
``Policy`` subclass and one :func:`register_method` call; ``tests/test_method_registry.py`` adds a toy
linear family that way and trains, saves, loads and rolls it out through ``sdp``'s own commands.

Methods from outside the package, as tasks (:mod:`sdp_cli.tasks`): a file passed with ``sdp --plugin FILE.py``
that calls :func:`register_method`, or an installed package's entry point in the group ``sdp.methods`` naming a
function that does (called when the registry is first imported)::

    [project.entry-points."sdp.methods"]
    chunk-mlp = "my_methods.chunk_mlp:register"

A plugin cannot replace a built-in method; one that fails is one line on stderr, the other methods stay usable.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import sys
from dataclasses import dataclass

from sdp_cli.errors import SdpError


@dataclass(frozen=True)
class Method:
    name: str
    policy: object          # a Policy subclass, or "module:Class" imported on first use
    sobolev: bool
    chunked: bool
    description: str = ""

    @property
    def policy_class(self):
        """The :class:`~sdp_cli.policy.base.Policy` subclass of this method."""
        if not isinstance(self.policy, str):
            return self.policy
        module, _, name = self.policy.partition(":")
        cls = getattr(importlib.import_module(module), name)
        if bool(cls.chunked) != self.chunked:
            raise SdpError(f"method {self.name!r}: {self.policy} is {'' if cls.chunked else 'not '}chunked, "
                           f"registered as {'' if self.chunked else 'not '}chunked")
        return cls


_REGISTRY: dict[str, Method] = {}


def register_method(name: str, policy, sobolev: bool, description: str = "", chunked: bool | None = None) -> Method:
    """Make ``name`` a method (``sdp train --method name``) trained and run by ``policy`` (a Policy subclass,
    or ``"module:Class"`` with ``chunked`` given, imported when first used); re-registering replaces it."""
    if not name or not name.replace("_", "").isalnum():
        raise SdpError(f"method names are identifiers, got {name!r}")
    if isinstance(policy, str):
        if chunked is None:
            raise SdpError(f"method {name!r}: a policy named by string needs chunked=True/False")
    else:
        chunked = bool(policy.chunked)
    m = Method(name, policy, bool(sobolev), bool(chunked), description)
    _REGISTRY[name] = m
    return m


def get_method(name: str) -> Method:
    if name not in _REGISTRY:
        raise SdpError(f"method must be one of {', '.join(_REGISTRY)}; got {name!r}")
    return _REGISTRY[name]


def method_names() -> tuple[str, ...]:
    return tuple(_REGISTRY)


def make_policy(config, dims: dict):
    """A fresh policy of ``config.method`` (untrained, normalizer at its defaults): ``(config, dims) -> Policy``."""
    return get_method(config.method).policy_class(config, dims)


def _register_builtin() -> None:
    diffusion, mlp = "sdp_cli.policy.diffusion:DiffusionUnetPolicy", "sdp_cli.policy.mlp:MLPPolicy"
    register_method("sdp", diffusion, sobolev=True, chunked=True, description="Sobolev diffusion policy, eq. (6)")
    register_method("dp", diffusion, sobolev=False, chunked=True, description="diffusion policy, eq. (2)")
    register_method("pddp", mlp, sobolev=False, chunked=False, description="MLP regression on the TO data")
    register_method("pddp_s", mlp, sobolev=True, chunked=False, description="MLP with the Sobolev term of eq. (4)")


_register_builtin()
_BUILTIN = dict(_REGISTRY)

#: the entry-point group of installed packages' methods
ENTRY_POINT_GROUP = "sdp.methods"


def _load_entry_points() -> None:
    """Call every ``sdp.methods`` entry point's function (it registers methods); built-in names are restored
    and a failing plugin leaves the registry as it was, each with one line on stderr."""
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        before = dict(_REGISTRY)
        try:
            ep.load()()
        except Exception as e:  # noqa: BLE001 - someone else's package: one line, not a traceback
            _REGISTRY.clear()
            _REGISTRY.update(before)
            print(f"sdp: ignoring plugin methods {ep.name!r} ({ep.value}): {type(e).__name__}: {e}", file=sys.stderr)
            continue
        for name, m in _BUILTIN.items():
            if _REGISTRY.get(name) is not m:
                _REGISTRY[name] = m
                print(f"sdp: ignoring plugin method {name!r} ({ep.value}): a built-in method has that name",
                      file=sys.stderr)


_load_entry_points()

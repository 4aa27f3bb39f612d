"""Task registry: ``--task`` accepts only the names registered here."""

from __future__ import annotations

import functools
from typing import Callable

from sdp_cli.errors import SdpError
from sdp_cli.tasks.base import Task

_REGISTRY: dict[str, tuple[Callable[..., Task], str]] = {}


def register(name: str, factory: Callable[..., Task], description: str) -> None:
    """Register a task factory under ``name`` (``factory(**options) -> Task``)."""
    _REGISTRY[name] = (factory, description)


def task_names() -> list[str]:
    return sorted(_REGISTRY)


def task_descriptions() -> dict[str, str]:
    return {k: v[1] for k, v in sorted(_REGISTRY.items())}


@functools.lru_cache(maxsize=None)
def _make(name: str, options: tuple) -> Task:
    return _REGISTRY[name][0](**dict(options))


def get_task(name: str, **options) -> Task:
    """The task instance for ``name`` (cached per process and options)."""
    if name not in _REGISTRY:
        raise SdpError(f"unknown task {name!r}; valid tasks: {', '.join(task_names())}")
    try:
        return _make(name, tuple(sorted(options.items())))
    except TypeError as e:
        raise SdpError(f"invalid option for task {name!r}: {e}") from None


def _register_builtin() -> None:
    from sdp_cli.tasks.pendulum import PendulumTask

    register("pendulum", lambda **kw: PendulumTask(n_links=1, **kw),
             "single pendulum swing-up, torque control, |u| <= 25")
    register("double_pendulum", lambda **kw: PendulumTask(n_links=2, **kw),
             "double pendulum swing-up, torque control, |u| <= 25 per joint")
    _register_ur5_quadrotor()


def _register_ur5_quadrotor() -> None:
    from sdp_cli.tasks.quadrotor import COLUMNS, QuadrotorTask
    from sdp_cli.tasks.ur5 import VARIANTS, Ur5Task

    init = {False: "q0 near the home pose", True: "q0 anywhere in [-pi, pi]^6"}
    tgt = {False: "fixed ee target", True: "random reachable ee target"}
    for name, (r_init, r_tgt) in VARIANTS.items():
        register(name, lambda r_init=r_init, r_tgt=r_tgt, **kw: Ur5Task(r_init=r_init, r_tgt=r_tgt, **kw),
                 f"UR5 reach (r_init={int(r_init)}, r_tgt={int(r_tgt)}): {init[r_init]}, {tgt[r_tgt]}; "
                 "torque limits")
    for n in COLUMNS:
        register(f"quadrotor-{n}", lambda n=n, **kw: QuadrotorTask(n_obstacles=n, **kw),
                 f"hector quadrotor to a goal at the same height, {n} column obstacles, floor/ceiling, "
                 "thrust bounds")
    register("quadrotor", lambda **kw: QuadrotorTask(n_obstacles=0, name="quadrotor", **kw),
             "alias of quadrotor-0 (no obstacles)")


_register_builtin()

__all__ = ["Task", "get_task", "register", "task_names", "task_descriptions"]

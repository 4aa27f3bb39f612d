"""Task registry: ``--task`` accepts only the names registered here.

Built-in tasks register below. A task of your own is a :class:`Task` subclass registered in one of
two ways, after which every command (``collect``, ``train``, ``rollout``, ``refine``, ``evaluate``,
``loop``, ``pipeline``, ``check-task``) and the task contract checks accept its name:

- an installed package declares an entry point in the group ``sdp.tasks``: the entry point's name is
  the task name and its object a factory ``factory(**options) -> Task`` (a Task subclass is one),
  e.g. in the package's ``pyproject.toml``::

      [project.entry-points."sdp.tasks"]
      cartpole = "my_robots.tasks:CartPoleTask"

  loaded when first used (``sdp tasks`` lists it without importing it);
- for quick work, a Python file that calls :func:`register` (and/or
  :func:`sdp_cli.policy.registry.register_method`: the same file may add methods):
  ``sdp --plugin my_task.py collect --task my-task ...`` (``--task-module``, its older name, still works).
  The file's path is added to the
  environment variable ``SDP_TASK_MODULES`` (paths separated by ``os.pathsep``), which worker
  processes, sub-commands and DVC stages inherit; set it yourself to make a file's tasks known to
  every ``sdp`` command.

A plugin cannot replace a built-in task name. Artifacts record the task's name and identity
(``model_id``), so a dataset or policy of a plugin task is loaded only where the plugin is registered.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path
from typing import Callable

from sdp_cli.errors import SdpError
from sdp_cli.tasks.base import Task
from sdp_cli.tasks.pendulum import PendulumTask
from sdp_cli.tasks.quadrotor import COLUMNS, QuadrotorTask
from sdp_cli.tasks.ur5 import VARIANTS, Ur5Task

_REGISTRY: dict[str, tuple[Callable[..., Task], str]] = {}
ENTRY_POINT_GROUP = "sdp.tasks"
TASK_MODULES_ENV = "SDP_TASK_MODULES"
_BUILTIN: set[str] = set()
_LOADED_FILES: set[str] = set()


def register(name: str, factory: Callable[..., Task], description: str) -> None:
    """Register a task factory under ``name`` (``factory(**options) -> Task``); a built-in name is refused."""
    if name in _BUILTIN:
        raise SdpError(f"task {name!r} is built in; register your task under another name")
    if not name or any(c.isspace() or c in "/\\" for c in name):
        raise SdpError(f"task names have no spaces or slashes, got {name!r}")
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
        raise SdpError(f"unknown task {name!r}; valid tasks: {', '.join(task_names())} (a task of your own: "
                       f"install its package (entry points {ENTRY_POINT_GROUP!r}) or pass --plugin FILE.py (or "
                       "--task-module FILE.py))")
    try:
        return _make(name, tuple(sorted(options.items())))
    except TypeError as e:
        raise SdpError(f"invalid option for task {name!r}: {e}") from None


def _entry_point_factory(ep: importlib.metadata.EntryPoint) -> Callable[..., Task]:
    def factory(**options) -> Task:
        try:
            obj = ep.load()
        except Exception as e:  # noqa: BLE001 - a broken plugin is the user's one-line error
            raise SdpError(f"task {ep.name!r}: entry point {ep.value!r} failed to load: {type(e).__name__}: {e}") \
                from None
        task = obj(**options)
        if not isinstance(task, Task):
            raise SdpError(f"task {ep.name!r}: entry point {ep.value!r} returned {type(task).__name__}, not a Task")
        return task
    return factory


def _load_entry_points() -> None:
    """Register the tasks of installed packages (group ``sdp.tasks``); built-in names win."""
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _BUILTIN:
            print(f"sdp: ignoring plugin task {ep.name!r} ({ep.value}): a built-in task has that name",
                  file=sys.stderr)
            continue
        dist = getattr(ep, "dist", None)
        register(ep.name, _entry_point_factory(ep), f"{ep.value} (plugin{' ' + dist.name if dist else ''})")


def load_task_module(path: str | os.PathLike) -> list[str]:
    """Import a Python file that registers tasks and/or methods (``sdp --plugin FILE.py``, alias ``--task-module``)
    and return the task names it
    added; its absolute path joins ``SDP_TASK_MODULES`` so that worker processes load it too."""
    p = Path(path).expanduser().resolve()
    if not p.is_file() or p.suffix != ".py":
        raise SdpError(f"--plugin {path}: not a Python file")
    key = str(p)
    before = set(_REGISTRY)
    if key not in _LOADED_FILES:
        mod_name = "sdp_task_module_" + hashlib.sha256(key.encode()).hexdigest()[:12]
        spec = importlib.util.spec_from_file_location(mod_name, p)
        module = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = module    # classes defined there pickle by this name in the same process
        try:
            spec.loader.exec_module(module)
        except SdpError:
            sys.modules.pop(mod_name, None)
            raise
        except Exception as e:  # noqa: BLE001 - the user's file: one line, not a traceback
            sys.modules.pop(mod_name, None)
            raise SdpError(f"--plugin {path} failed: {type(e).__name__}: {e}") from None
        _LOADED_FILES.add(key)
    listed = [s for s in os.environ.get(TASK_MODULES_ENV, "").split(os.pathsep) if s]
    if key not in listed:
        os.environ[TASK_MODULES_ENV] = os.pathsep.join(listed + [key])
    return sorted(set(_REGISTRY) - before)


def _load_env_modules() -> None:
    for f in [s for s in os.environ.get(TASK_MODULES_ENV, "").split(os.pathsep) if s]:
        load_task_module(f)


def _register_builtin() -> None:
    register("pendulum", lambda **kw: PendulumTask(n_links=1, **kw),
             "single pendulum swing-up, torque control, |u| <= 25")
    register("double_pendulum", lambda **kw: PendulumTask(n_links=2, **kw),
             "double pendulum swing-up, torque control, |u| <= 25 per joint")
    _register_ur5_quadrotor()


def _register_ur5_quadrotor() -> None:
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
_BUILTIN.update(_REGISTRY)
_load_entry_points()
try:
    _load_env_modules()
except SdpError as _e:   # a stale SDP_TASK_MODULES entry: say so once, keep the other tasks usable
    print(f"sdp: {_e} (from {TASK_MODULES_ENV})", file=sys.stderr)

__all__ = ["Task", "get_task", "register", "load_task_module", "task_names", "task_descriptions",
           "ENTRY_POINT_GROUP", "TASK_MODULES_ENV"]

"""Locate example-robot-data's URDFs and build Pinocchio models from them.

``example-robot-data`` 6.x on PyPI ships only the data (its Python loaders moved to
``example-robot-data-loaders``, which pins ``example-robot-data==5.0.0``). We depend on
the data package alone and build the few models we need with ``pin.buildModelFromUrdf``;
``tests/test_dynamics.py`` checks that ``double_pendulum``, ``ur5`` and ``hector`` load.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import pinocchio as pin

from sdp_cli.errors import SdpError

#: robot name -> URDF path relative to ``robots/``, free-flyer root or not
URDFS = {
    "double_pendulum": ("double_pendulum_description/urdf/double_pendulum.urdf", False),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", False),
    "hector": ("hector_description/robots/quadrotor_base.urdf", True),
}


@functools.cache
def robots_dir() -> Path:
    """Folder ``.../share/example-robot-data/robots`` of the installed data package."""
    candidates = []
    if env := os.environ.get("EXAMPLE_ROBOT_DATA_DIR"):
        candidates.append(Path(env))
    for base in sys.path:
        candidates.append(Path(base) / "cmeel.prefix" / "share" / "example-robot-data" / "robots")
    for c in candidates:
        if (c / "double_pendulum_description").is_dir():
            return c
    raise SdpError("example-robot-data not found: pip install example-robot-data "
                   "(or set EXAMPLE_ROBOT_DATA_DIR to its robots/ folder)")


def load_model(name: str) -> pin.Model:
    """A fresh :class:`pinocchio.Model` of an example-robot-data robot."""
    if name not in URDFS:
        raise SdpError(f"unknown robot {name!r}; known: {', '.join(sorted(URDFS))}")
    rel, free_flyer = URDFS[name]
    path = str(robots_dir() / rel)
    if free_flyer:
        return pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer())
    return pin.buildModelFromUrdf(path)

"""A task's identity (``model_id``): artifacts made for another definition of a task name are
refused, and a changed constant compiles a new optimizer library instead of reusing a stale one."""

from __future__ import annotations

import numpy as np
import pytest

import sdp_cli.tasks.pendulum as pendulum_module
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.base import check_task_params
from sdp_cli.tasks.pendulum import PendulumTask


def _changed(monkeypatch, **consts) -> PendulumTask:
    for k, v in consts.items():
        monkeypatch.setattr(pendulum_module, k, v)
    return PendulumTask(n_links=2)


def test_model_id_is_stable_and_tracks_every_constant(monkeypatch):
    base = PendulumTask(n_links=2)
    assert base.model_id == get_task("double_pendulum").model_id == PendulumTask(n_links=2).model_id
    ids = {base.model_id}
    for consts in ({"W_GOAL": 11.0}, {"W_U": 0.2}, {"W_GOAL_T": 20.0}, {"BODY_MASS": 1.1}, {"LINK_LENGTH": 0.9},
                   {"U_MAX": 20.0}):
        with monkeypatch.context() as m:
            ids.add(_changed(m, **consts).model_id)
    assert len(ids) == 7
    assert PendulumTask(n_links=2, dt=0.02).model_id not in ids


def test_artifact_of_another_definition_is_refused(monkeypatch, tmp_path):
    from sdp_cli.data.chunks import load_dataset
    from synthetic_dataset import write_dataset

    task = get_task("pendulum", T=20)
    path = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=1, T=20)
    load_dataset(path, require_gains=False)                     # made here: accepted
    stored = dict(task.params(), model_id="0123456789abcdef")   # as an older sdp would have written it
    with pytest.raises(SdpError, match="another definition of task 'pendulum'"):
        check_task_params(task, stored, "dataset")
    with pytest.raises(SdpError, match="differ .* in: T"):
        check_task_params(task, dict(task.params(), T=30), "dataset")
    # through the loader: the dataset's recorded identity differs from the task built now
    with monkeypatch.context() as m:
        m.setattr(pendulum_module, "W_U", 0.5)
        get_task.__globals__["_make"].cache_clear()
        with pytest.raises(SdpError, match="another definition"):
            load_dataset(path, require_gains=False)
    get_task.__globals__["_make"].cache_clear()


def test_changed_constant_compiles_a_new_library(monkeypatch, tmp_path):
    from sdp_cli.trajopt.solver import TrajOptSolver

    monkeypatch.setenv("SDP_CACHE_DIR", str(tmp_path))
    task = PendulumTask(n_links=1, T=20)
    TrajOptSolver(task, 20, "fatrop", 100, 1e-6, 1e-6, True)
    libs = set((tmp_path / "jit").glob("*.so"))
    assert len(libs) == 1
    TrajOptSolver(PendulumTask(n_links=1, T=20), 20, "fatrop", 100, 1e-6, 1e-6, True)   # same problem: reused
    assert set((tmp_path / "jit").glob("*.so")) == libs
    _changed(monkeypatch, W_U=0.3)
    changed_1 = PendulumTask(n_links=1, T=20)
    s = TrajOptSolver(changed_1, 20, "fatrop", 100, 1e-6, 1e-6, True)
    new = set((tmp_path / "jit").glob("*.so")) - libs
    assert len(new) == 1 and s.jitted                         # same name prefix, new code hash
    assert next(iter(new)).name.split("_")[:-1] == next(iter(libs)).name.split("_")[:-1]
    xi = changed_1.sample_xi(np.random.default_rng(0))
    assert np.isfinite(s.solve(xi, *changed_1.naive_guess(xi)).cost)


def test_results_version_1_ur5_and_quadrotor_artifacts_are_refused(monkeypatch):
    """Datasets and policies made for the definitions before issue "A perfect learner..." (aligator's
    terminal-only UR5 reach, the quadrotor without its arrival term, random UR5 targets up to full
    extension) are refused by identity, not silently reused."""
    import sdp_cli.tasks.ur5 as ur5_module
    from sdp_cli.tasks.ur5 import Ur5Task

    now = Ur5Task(r_tgt=True)
    with monkeypatch.context() as m:      # aligator's running weights: no ee term, 1e-2 ||v||^2
        m.setattr(ur5_module, "W_EE", 0.0)
        m.setattr(ur5_module, "W_V", 1e-2)
        old = Ur5Task(r_tgt=True)
        stored = old.params()
    assert stored["model_id"] != now.model_id
    with pytest.raises(SdpError, match="another definition of task 'ur5-rtgt'"):
        check_task_params(now, stored, "dataset")
    # same costs, targets sampled up to the arm's full reach (results version 2): another distribution
    v2 = dict(now.params())
    v2.pop("target_region")
    with pytest.raises(SdpError, match="differ .* in: target_region"):
        check_task_params(now, v2, "dataset")
    quad = get_task("quadrotor-0")
    with pytest.raises(SdpError, match="another definition of task 'quadrotor-0'"):
        check_task_params(quad, get_task("quadrotor-0", arrival=False).params(), "policy")

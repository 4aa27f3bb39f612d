"""``sdp rollout``: Algorithm 2, batched over test instances.

All ``n`` instances advance together: one network call per denoising step for the whole
batch (diffusion policies) or one per time step (MLP policies); the dynamics of the batch
are stepped by the task's casadi step function mapped over instances (compiled casadi VM,
identical to Pinocchio's semi-implicit Euler to ~1e-13, see tests/test_dynamics.py).

Actions: torque policies (``action == "u"``) play ``tau_0[T_o : T_o + T_a]`` directly,
saturated at the control bounds (the actuators cannot do more); state policies predict
``g(x_{t+1}), ...`` and the controls come from :meth:`Task.controls_from_action` (inverse
dynamics: RNEA for fully actuated arms, thrust allocation for the quadrotor).

Divergence (a NaN state, a state coordinate above ``DIVERGENCE_STATE``, or a cost above
``DIVERGENCE_COST``) is recorded, not raised:
the instance's remaining states are NaN and ``diverged`` is set.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from sdp_cli.data.artifacts import portable_path, save_npz
from sdp_cli.errors import SdpError
from sdp_cli.rules import check_fields, rule
from sdp_cli.seeds import TEST_SEED_BASE, check_seed  # noqa: F401 (TEST_SEED_BASE re-exported)
from sdp_cli.tasks import Task
from sdp_cli.tasks.conversion import check_conversion
from sdp_cli.policy import load_policy
from sdp_cli.data.artifacts import check_writable

DIVERGENCE_COST = 1e5
#: a state coordinate beyond this (rad, rad/s, m, m/s) is a diverged simulation: the faithful
#: pendulum costs do not see velocities, so a cost threshold alone misses a spinning pendulum
DIVERGENCE_STATE = 1e4
# the test set: xi from rng([TEST_SEED_BASE + seed, i]), disjoint from training collections,
# whose seeds stay below TEST_SEED_BASE (sdp_cli.seeds)


@dataclass(frozen=True)
class RolloutConfig:
    n: int = field(default=50, metadata=rule(ge=1))
    seed: int = 0
    t_a: int | None = field(default=None, metadata=rule(ge=1))  # default T_h - T_o
    k_rollout: int | None = field(default=None, metadata=rule(ge=1))  # default K
    #: predicted chunk -> controls (sdp_cli.tasks.conversion); None: the task's default
    conversion: str | None = None

    def __post_init__(self):
        check_seed(self.seed, "test seed")
        check_fields(self)
        check_conversion(self.conversion)

    def validate(self, policy) -> "RolloutConfig":
        """The settings a rollout of ``policy`` uses: ``t_a`` in ``[1, policy.max_t_a]`` (default the
        maximum), the sampler's ``k_rollout`` (``policy.sampler_options``: default K; refused for a family
        without a sampler), and the conversion (None where the actions are controls: nothing converts them)."""
        hi = policy.max_t_a
        t_a = self.t_a if self.t_a is not None else hi
        if not 1 <= t_a <= hi:
            what = "T_h - T_o" if hi > 1 else "one control per state"
            raise SdpError(f"t_a must be in [1, {hi}] for this policy ({what}), got {t_a}")
        k = policy.sampler_options(self.k_rollout).get("k_rollout")
        conversion = (self.conversion or policy.task.default_conversion) if policy.task.action != "u" else None
        return RolloutConfig(self.n, self.seed, t_a, k, conversion)


def evaluation_xis(task: Task, n: int, seed: int) -> np.ndarray:
    """The fixed evaluation set ``(n, n_xi)``: disjoint from any training seed < TEST_SEED_BASE."""
    return np.stack([task.sample_xi(np.random.default_rng([TEST_SEED_BASE + int(seed), i])) for i in range(n)])


def step_batch(task: Task, X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """One dynamics step for a batch: ``X (B, nx)``, ``U (B, nu)`` -> ``(B, nx)``."""
    return task.step_map(len(X))(X.T, U.T).full().T


def instance_generators(seed: int, indices, device="cpu") -> list[torch.Generator]:
    """One torch generator per instance, seeded by ``(seed, index)``: the rollout of an instance
    does not depend on which other instances share its batch."""
    return [torch.Generator(device=device).manual_seed(
        int(np.random.SeedSequence([int(seed), int(i)]).generate_state(1, np.uint64)[0] >> 1)) for i in indices]


def rollout_policy(policy, xis: np.ndarray, config: RolloutConfig,
                   generators: list[torch.Generator] | None = None,
                   on_step: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """Algorithm 2 for a batch of instances ``xis (n, n_xi)``; returns ``X (n, T+1, nx)``, ``U (n, T, nu)``.

    ``generators``: one per instance (see :func:`instance_generators`); default seeded by
    ``(config.seed, i)``.
    """
    task: Task = policy.task
    n, T = len(xis), task.T
    if generators is None:
        generators = instance_generators(config.seed, range(n))   # CPU: a seed means the same on a GPU
    X = np.full((n, T + 1, task.nx), np.nan)
    U = np.full((n, T, task.nu), np.nan)
    X[:, 0] = np.stack([task.initial_state(xi) for xi in xis])
    u_prev = np.zeros((n, task.nu))
    alive = np.ones(n, dtype=bool)
    t = 0
    with np.errstate(all="ignore"):
        while t < T and alive.any():
            idx = np.flatnonzero(alive)
            sampler = {} if config.k_rollout is None else {"k_rollout": config.k_rollout}
            acts = policy.plan(xis[idx], X[idx, t], u_prev[idx], generator=[generators[i] for i in idx],
                               **sampler)                                           # (B, n, A), n >= t_a
            n_play = min(config.t_a, T - t)
            controller = task.chunk_controller(X[idx, t], acts[:, :n_play], config.conversion)
            for s in range(n_play):
                x = X[idx, t + s]
                u = controller(x, s)
                x_next = step_batch(task, x, u)
                bad = ~np.all(np.isfinite(x_next), axis=1) | (np.abs(x_next).max(axis=1) > DIVERGENCE_STATE)
                U[idx, t + s] = u
                X[idx, t + s + 1] = np.where(bad[:, None], np.nan, x_next)
                u_prev[idx] = u
            t += config.t_a
            alive &= np.all(np.isfinite(X[:, min(t, T)]), axis=1)
            if on_step:
                on_step(min(t, T), T)
    return {"X": X, "U": U}


def evaluate_rollouts(task: Task, X: np.ndarray, U: np.ndarray, xis: np.ndarray) -> dict[str, np.ndarray]:
    """True cost and its terminal term (``terminal_cost``), constraint violation (the max, and per constraint
    group: ``violation_<group>``, e.g. ``violation_obstacles``), divergence and goal flags per instance ``(N,)``."""
    n = len(xis)
    cost, goal = np.full(n, np.inf), np.full(n, np.inf)
    groups = task.violations_per_instance(X, U, xis)
    viol = np.max(np.stack(list(groups.values())), axis=0)
    for i in range(n):
        if np.all(np.isfinite(X[i])) and np.all(np.isfinite(U[i])):
            cost[i] = task.cost(X[i], U[i], xis[i])
            try:
                goal[i] = task.goal_distance(X[i, -1], xis[i])
            except NotImplementedError:
                goal[i] = np.nan
    diverged = ~np.isfinite(cost) | (cost > DIVERGENCE_COST)
    terminal = np.where(np.isfinite(cost), task.terminal_costs(X, xis), np.inf)
    return {"cost": cost, "terminal_cost": terminal, "max_violation": viol, "goal_distance": goal, "diverged": diverged,
            "reached": (goal <= task.goal_tolerance) & ~diverged, **{f"violation_{g}": v for g, v in groups.items()}}


def _dataset_record(info: dict, out: str | os.PathLike) -> dict:
    """The policy's training-dataset record with its path relative to the rollouts' folder."""
    return {**info, "path": portable_path(info["path"], Path(out).parent)} if info.get("path") else dict(info)


def rollout(policy_path: str | os.PathLike, out: str | os.PathLike, config: RolloutConfig,
            task_name: str | None = None, device: str = "cpu",
            on_step: Callable[[int, int], None] | None = None) -> tuple[Path, dict]:
    """Load a policy, roll it out on the test set, write a ``rollout`` artifact."""
    policy = load_policy(policy_path, device=device)
    if task_name is not None and task_name != policy.task_name:
        raise SdpError(f"policy {policy_path} was trained on task {policy.task_name!r}, not {task_name!r}")
    config = config.validate(policy)

    check_writable(out)                    # before the work, not after it
    task = policy.task
    xis = evaluation_xis(task, config.n, config.seed)
    t0 = time.perf_counter()
    with torch.no_grad():
        traj = rollout_policy(policy, xis, config, on_step=on_step)
    wall = time.perf_counter() - t0
    ev = evaluate_rollouts(task, traj["X"], traj["U"], xis)
    arrays = {**traj, **ev, "xi": xis}
    ck_cfg = policy.config.to_dict() if hasattr(policy.config, "to_dict") else {}
    path = save_npz(out, arrays, kind="rollout", config={**asdict(config), "policy": portable_path(policy_path, Path(out).parent)},
                    device=str(policy.device), task=policy.task_name, task_options=policy.task_options,
                    task_params=task.params(), method=policy.method, policy_config=ck_cfg,
                    policy_epoch=policy.checkpoint_epoch, policy_dataset=_dataset_record(policy.dataset_info, out),
                    timing={"rollout_time": wall})
    summary = {"method": policy.method, "n": config.n, "mean_cost": float(np.mean(ev["cost"])),
               "median_cost": float(np.median(ev["cost"])), "diverged": int(ev["diverged"].sum()),
               "reached": int(ev["reached"].sum()), "rollout_time": wall}
    return path, summary

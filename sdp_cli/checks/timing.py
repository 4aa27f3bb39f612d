"""Is a task well-posed for a policy that does not see time? Timing of a TO optimum.

A chunked policy conditions on ``(x_t, u_{t-1}, xi)`` only: it cannot know how many steps remain.
If the optimum is only cheap when it stops at exactly ``T`` (a terminal-only reach at full speed),
the paper's cost turns into a stop-timing test that no such policy can pass. For one optimum
``(X, U)`` of instance ``xi`` this module measures (:func:`optimum_timing`):

- ``t_in``: the first time from which the goal distance stays within the task's tolerance;
- ``t_rest``: the first time from which the speed ``||v||`` stays <= ``REST_SPEED``;
- speed and goal distance at ``T``;
- the cost of playing the optimum's own actions ``k`` steps late (``a'_t = a_{t-k}``; for ``t < k``
  the action that holds ``x_0`` at rest) and early (``a'_t = a_{min(t+k, T-1)}``), relative to its
  cost. The shifted actions are played as one chunk through the task's conversion
  (:meth:`Task.chunk_controller`, the task's default unless ``conversion`` says otherwise) from the states
  actually reached, as a policy's rollout plays its chunks; torque actions are played directly (clipped).

:data:`WELL_POSED_LATE_RATIO`: a task is well-posed when one step late costs at most 2x the optimum.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.data.chunks import action_sequence
from sdp_cli.algorithm.rollout import step_batch
from sdp_cli.tasks import Task

REST_SPEED = 0.05           # ||v|| (rad/s, or m/s and rad/s) below which a state is at rest
WELL_POSED_LATE_RATIO = 2.0  # one step late may cost at most this multiple of the optimum
SHIFTS = (1, 2, 5)


def _first_for_good(ok: np.ndarray) -> int | None:
    """The first index from which ``ok`` holds to the end, or None."""
    bad = np.flatnonzero(~ok)
    if len(bad) == 0:
        return 0
    return None if bad[-1] == len(ok) - 1 else int(bad[-1] + 1)


def speed(task: Task, X: np.ndarray) -> np.ndarray:
    """``||v||`` along a trajectory (T+1,)."""
    return np.linalg.norm(np.asarray(X)[..., task.nq:], axis=-1)


def hold_action(task: Task, x0: np.ndarray) -> np.ndarray:
    """The action that keeps ``x0`` at rest: ``g(x0)`` for state actions; for torque, the controls of
    inverse dynamics where the task has it (gravity compensation), else zero."""
    if task.action != "u":
        return task.state_action(x0)
    try:
        return task.inverse_dynamics(x0, x0)
    except NotImplementedError:
        return np.zeros(task.nu)


def play_shifted(task: Task, X: np.ndarray, U: np.ndarray, k: int,
                 conversion: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Replay the optimum's actions shifted by ``k`` (> 0 late, < 0 early) as one chunk through the task's
    ``conversion`` (None: its default): ``(X', U')``."""
    T = len(U)
    A = U if task.action == "u" else action_sequence(task, X[None], U[None], task.action)[0, 1:]   # a_t -> x_{t+1}
    hold = hold_action(task, X[0])
    shifted = np.stack([hold if t - k < 0 else A[min(t - k, T - 1)] for t in range(T)])
    controller = task.chunk_controller(X[:1], shifted[None], conversion)
    Xs = np.empty_like(X)
    Us = np.empty_like(U)
    Xs[0] = X[0]
    for t in range(T):
        u = controller(Xs[t][None], t)[0]
        Us[t] = u
        Xs[t + 1] = step_batch(task, Xs[t][None], u[None])[0]
    return Xs, Us


def optimum_timing(task: Task, X: np.ndarray, U: np.ndarray, xi: np.ndarray, shifts=SHIFTS,
                   conversion: str | None = None) -> dict:
    """The timing record of one optimum (see the module docstring)."""
    X, U = np.asarray(X, float), np.asarray(U, float)
    dist = np.array([task.goal_distance(x, xi) for x in X])
    v = speed(task, X)
    cost = task.cost(X, U, xi)
    row = {"cost": cost, "t_in": _first_for_good(dist <= task.goal_tolerance), "t_rest": _first_for_good(v <= REST_SPEED),
           "speed_T": float(v[-1]), "dist_T": float(dist[-1]), "T": len(U)}
    for k in shifts:
        for sign, name in ((1, "late"), (-1, "early")):
            Xs, Us = play_shifted(task, X, U, sign * k, conversion)
            c = task.cost(Xs, Us, xi) if np.all(np.isfinite(Xs)) else np.inf
            row[f"{name}{k}"] = c / cost
    return row

"""A perfect learner: the nearest training chunk, with the policy protocol the rollout uses.

:class:`MemorizerPolicy` holds every chunk of a dataset (:class:`sdp_cli.data.chunks.ChunkDataset`, the
samples a diffusion policy trains on) and answers ``predict_chunk(xi, x, u_prev)`` with the chunk whose
condition ``(x_t, u_{t-1}, xi)`` is nearest (Euclidean, each coordinate scaled by its spread over the
data). Rolled out by :func:`sdp_cli.rollout.rollout_policy` on its own training instances, it must
reproduce their TO cost: if it does not, no learner can, and the experiment (chunk sampling, rollout
conventions, the task) measures itself rather than the method. ``sdp check-task`` and
``tests/test_memorizer.py`` run it.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.data.chunks import ChunkDataset, task_with_action
from sdp_cli.tasks import Task


class MemorizerPolicy:
    """Nearest-neighbour lookup of training chunks ``(N S, T_h, A)`` (unnormalized).

    ``is_diffusion``, ``T_h``, ``T_o``, ``K``, ``task`` and ``predict_chunk`` are what
    :class:`sdp_cli.rollout.RolloutConfig` and :func:`sdp_cli.rollout.rollout_policy` use."""

    is_diffusion = True
    K = 1

    def __init__(self, task: Task, arrays: dict, T_h: int, T_o: int = 1, action: str | None = None):
        ds = ChunkDataset(task, arrays, T_h, T_o, action=action, with_jacobians=False)
        self.task = task_with_action(task, ds.action)
        self.T_h, self.T_o = ds.T_h, ds.T_o
        self.chunks = ds.tau0.reshape((-1,) + ds.tau0.shape[2:])                 # (N S, T_h, A)
        self.keys = self._key(ds.x_hist[:, :, 0], ds.obs[:, :, 0, -task.nu:], ds.xi).reshape(len(self.chunks), -1)
        spread = self.keys.std(axis=0)
        self.scale = np.where(spread > 1e-12, spread, 1.0)

    @staticmethod
    def _key(x, u_prev, xi) -> np.ndarray:
        """The condition ``(x, u_{t-1}, xi)`` in plain coordinates (a quaternion's 4 included):
        (..., nx + nu + n_xi)."""
        return np.concatenate([np.asarray(x, dtype=float), np.asarray(u_prev, dtype=float),
                               np.asarray(xi, dtype=float)], axis=-1)

    def predict_chunk(self, xis, x, u_prev, generator=None, k_rollout=None) -> np.ndarray:
        """The nearest training chunk to each condition: ``(B, n_xi), (B, nx), (B, nu) -> (B, T_h, A)``."""
        q = self._key(x, u_prev, xis) / self.scale
        keys = self.keys / self.scale
        d = ((q[:, None, :] - keys[None]) ** 2).sum(-1)                          # (B, N S)
        return self.chunks[np.argmin(d, axis=1)].copy()

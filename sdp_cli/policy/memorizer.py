"""A perfect learner: the nearest training chunk, with the policy protocol the rollout uses.

:class:`MemorizerPolicy` holds every chunk of a dataset (:class:`sdp_cli.data.chunks.ChunkDataset`, the
samples a diffusion policy trains on) and answers ``predict_chunk(xi, x, u_prev)`` with the chunk whose
condition ``(x_t, u_{t-1}, xi)`` is nearest (Euclidean, each coordinate scaled by its spread over the
data). Rolled out by :func:`sdp_cli.algorithm.rollout.rollout_policy` on its own training instances, it must
reproduce their TO cost: if it does not, no learner can, and the experiment (chunk sampling, rollout
conventions, the task) measures itself rather than the method. ``sdp check-task`` and
``tests/test_memorizer.py`` run it.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.data.chunks import ChunkDataset, task_with_action
from sdp_cli.policy.base import ChunkPlanning
from sdp_cli.tasks import Task


class MemorizerPolicy(ChunkPlanning):
    """Nearest-neighbour lookup of training chunks ``(N S, T_h, A)`` (unnormalized).

    A chunked planner (:class:`~sdp_cli.policy.base.ChunkPlanning`: ``plan``, ``max_t_a``, ``sampler_options``
    from ``T_h``, ``T_o``, ``K = 1`` and ``predict_chunk``): what :func:`sdp_cli.algorithm.rollout.rollout_policy` uses."""

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


class NoisyMemorizer(ChunkPlanning):
    """The memorizer's chunk plus noise ``sigma * scale`` (``scale (A,)``: the normalizer's half-range of each
    action coordinate, so sigma is in the units the networks see); rows ``[:T_o]`` (the inpainted history) stay
    exact. ``kind``: ``white`` (independent per row and coordinate) or ``offset`` (one draw per chunk and
    coordinate, held over its rows). A stand-in for a learner that is nearly right (``sdp check-task``'s
    noise-tolerance row, ``bench/action_noise.py``)."""

    K = 1

    def __init__(self, base: MemorizerPolicy, scale: np.ndarray, sigma: float, kind: str = "white", seed: int = 0):
        if kind not in ("white", "offset"):
            raise ValueError(f"noise kind must be white or offset, got {kind!r}")
        self.base, self.scale, self.sigma, self.kind = base, np.asarray(scale, dtype=float), float(sigma), kind
        self.task, self.T_h, self.T_o = base.task, base.T_h, base.T_o
        self.rng = np.random.default_rng(seed)

    def predict_chunk(self, xis, x, u_prev, generator=None, k_rollout=None) -> np.ndarray:
        """The nearest training chunk plus noise: ``(B, n_xi), (B, nx), (B, nu) -> (B, T_h, A)``."""
        tau = self.base.predict_chunk(xis, x, u_prev)
        B, H, A = tau.shape
        shape = (B, H, A) if self.kind == "white" else (B, 1, A)
        noise = np.broadcast_to(self.rng.standard_normal(shape), (B, H, A)).copy()
        noise[:, : self.T_o] = 0.0
        return tau + self.sigma * noise * self.scale

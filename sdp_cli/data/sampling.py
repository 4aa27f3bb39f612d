"""Epochs as the paper defines them: which samples each training step sees.

An epoch is ``E`` samples (``E = |D| (T - T_h) / T_h`` chunks for the diffusion policies,
``|D| T`` pairs for the MLPs; :meth:`ChunkDataset.epoch_size`, :meth:`PairDataset.epoch_size`)
drawn **without replacement** from the ``n`` stored samples (every chunk start of every
trajectory), split into ``ceil(E / B)`` batches of ``B``, the last one smaller.

Each epoch's permutation comes from its own CPU generator seeded by ``(seed, epoch)``, so a
run resumed mid-epoch sees the same batches as an uninterrupted one, and the same seed
draws the same samples on the CPU and on a GPU.
"""

from __future__ import annotations

import math

import torch


def steps_per_epoch(E: int, batch_size: int) -> int:
    """``ceil(E / B)``."""
    return math.ceil(E / batch_size)


def epoch_indices(n: int, E: int, seed: int, epoch: int) -> torch.Tensor:
    """The ``min(E, n)`` distinct sample indices (CPU, int64) of epoch ``epoch``, in drawing order."""
    g = torch.Generator().manual_seed((int(seed) * 1_000_003 + int(epoch)) % (2**63 - 1))
    return torch.randperm(n, generator=g)[: min(E, n)]


def batch_indices(n: int, E: int, batch_size: int, seed: int, step: int) -> torch.Tensor:
    """Indices of training step ``step`` (0-based): batch ``step mod ceil(E / B)`` of epoch
    ``step // ceil(E / B)``; ``B`` samples, or fewer for an epoch's last batch."""
    spe = steps_per_epoch(E, batch_size)
    epoch, j = divmod(int(step), spe)
    return epoch_indices(n, E, seed, epoch)[j * batch_size:(j + 1) * batch_size]

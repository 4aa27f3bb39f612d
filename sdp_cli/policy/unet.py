"""Conditional 1D U-Net over action chunks, as in diffusion policy (Chi et al.).

Input ``tau_k (B, T_h, A)``, diffusion step ``k (B,)`` and a global condition
``cond (B, n_cond)`` (here ``(xi, o_hist)``); output ``(B, T_h, A)``. Structure: a sinusoidal
step embedding through an MLP, concatenated with ``cond``, conditions every residual
block by FiLM (per-channel scale and bias). Residual blocks are
Conv1d -> GroupNorm -> Mish twice; the down path halves the time axis between levels
(strided conv), the up path doubles it (transposed conv) and concatenates skip features.
``T_h`` must be divisible by ``2^(len(down_dims) - 1)``.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class StepEmbedding(nn.Module):
    """Sinusoidal embedding of the diffusion step, then Linear-Mish-Linear: (B,) -> (B, dim)."""

    def __init__(self, dim: int):
        super().__init__()
        half = dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half) / max(half - 1, 1))
        self.register_buffer("freqs", freqs, persistent=False)
        self.mlp = nn.Sequential(nn.Linear(2 * half, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        arg = k.float()[:, None] * self.freqs[None]
        return self.mlp(torch.cat([arg.sin(), arg.cos()], dim=-1))


class ConvBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish, length preserving."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int):
        super().__init__(nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2),
                         nn.GroupNorm(n_groups, c_out), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks with FiLM conditioning between them, plus a residual path."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.block1 = ConvBlock(c_in, c_out, kernel_size, n_groups)
        self.block2 = ConvBlock(c_out, c_out, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.c_out = c_out

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.block1(x)
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        h = self.block2(scale * h + bias)
        return h + self.residual(x)


class ConditionalUnet1D(nn.Module):
    """``forward(tau (B, T_h, A), k (B,), cond (B, n_cond)) -> (B, T_h, A)``."""

    def __init__(self, action_dim: int, cond_dim: int, down_dims=(24, 24, 32, 32), kernel_size: int = 5,
                 n_groups: int = 8, step_embed_dim: int = 64):
        super().__init__()
        self.step_embed = StepEmbedding(step_embed_dim)
        cdim = step_embed_dim + cond_dim
        dims = [action_dim, *down_dims]
        pairs = list(zip(dims[:-1], dims[1:]))
        blk = lambda a, b: FiLMResBlock(a, b, cdim, kernel_size, n_groups)
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(nn.ModuleList([blk(a, b), blk(b, b),
                                            nn.Identity() if last else nn.Conv1d(b, b, 3, 2, 1)]))
        d = down_dims[-1]
        self.mid = nn.ModuleList([blk(d, d), blk(d, d)])
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):
            self.up.append(nn.ModuleList([blk(2 * b, a), blk(a, a), nn.ConvTranspose1d(a, a, 4, 2, 1)]))
        self.final = nn.Sequential(ConvBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
                                   nn.Conv1d(down_dims[0], action_dim, 1))

    def forward(self, tau: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = torch.cat([self.step_embed(k), cond], dim=-1)
        x = tau.transpose(1, 2)
        skips = []
        for r1, r2, down in self.down:
            x = r2(r1(x, c), c)
            skips.append(x)
            x = down(x)
        for r in self.mid:
            x = r(x, c)
        for r1, r2, up in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = up(r2(r1(x, c), c))
        return self.final(x).transpose(1, 2)

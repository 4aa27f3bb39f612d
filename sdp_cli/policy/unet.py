"""Conditional 1D U-Net over action chunks, as in diffusion policy (Chi et al.); one network or R stacked.

Input ``tau_k (B, T_h, A)``, diffusion step ``k (B,)`` and a global condition
``cond (B, n_cond)`` (here ``(xi, o_hist)``); output ``(B, T_h, A)``. Structure: a sinusoidal
step embedding through an MLP, concatenated with ``cond``, conditions every residual
block by FiLM (per-channel scale and bias). Residual blocks are
Conv1d -> GroupNorm -> Mish twice; the down path halves the time axis between levels
(strided conv), the up path doubles it (transposed conv) and concatenates skip features.
``T_h`` must be divisible by ``2^(len(down_dims) - 1)``.

**Stacked (``members=R > 1``)**: R independent U-Nets of one architecture in one module, the training of R runs
at once (:mod:`sdp_cli.training.train_stack`): the paper's U-Net is tiny, so a step is mostly per-op overhead and R
networks stacked cost little more than one. The same layers and the same code, with every layer R-fold:
convolutions grouped (``groups=R``: member ``r``'s channels are the block ``[r C, (r + 1) C)``), GroupNorm over
``R x n_groups`` groups (a member's groups never mix with another's), linear layers batched
(:class:`StackedLinear`, weights ``(R, out, in)``). Shapes gain a member axis: ``tau (B, R, T_h, A)``,
``k (B, R)``, ``cond (B, R, n_cond)`` -> ``(B, R, T_h, A)`` (the batch axis is shared; members with fewer
samples are padded by the caller). Member ``r`` computes what a solo network with its weights computes, to float32
rounding (the grouped kernels sum in another order); :func:`stack_members` builds a stack from solo networks and
:func:`member_state_dict` gives a member's weights back as a solo state dict (a stacked run's checkpoint is a
solo one). With ``members=1`` every layer is the plain one: the solo network, its state dict and its numerics.

:meth:`ConditionalUnet1D.forward_jvp` propagates a tangent alongside the primal by hand
(linear layers run once on the primal and tangent stacked along the batch; GroupNorm and
Mish are fused primal+tangent ops with closed-form backward passes, :mod:`.tangent_ops`). It returns the same ``(y, dy)`` as
``torch.func.jvp`` (tested) but is plain reverse-differentiable ops, about twice as fast
as torch's forward-mode AD here and compatible with ``torch.compile``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from sdp_cli.policy.tangent_ops import group_norm_jvp, mish_jvp
from sdp_cli.policy.compiling import compiled


# ------------------------------------------------------- tangent propagation
def _linear_t(layer: nn.Module, x: torch.Tensor, xd: torch.Tensor | None):
    """A linear layer (Conv1d, ConvTranspose1d, Linear) on a primal and its tangent."""
    if xd is None:
        return layer(x), None
    B = x.shape[0]
    out = layer(torch.cat([x, xd], dim=0))
    y, yd = out[:B], out[B:]
    if layer.bias is not None:   # a convolution's bias is per channel (dim 1); a linear layer's is the last dim
        yd = yd - (layer.bias[:, None] if isinstance(layer, (nn.Conv1d, nn.ConvTranspose1d)) else layer.bias)
    return y, yd


def _sub_batch(op, fused, x, xd):
    """Tangents may cover only the first ``xd.shape[0]`` samples of the batch."""
    if xd is None:
        return op(x), None
    n = xd.shape[0]
    if n == x.shape[0]:
        return fused(x, xd)
    y, yd = fused(x[:n], xd)
    return torch.cat([y, op(x[n:])], dim=0), yd


def _mish_t(x: torch.Tensor, xd: torch.Tensor | None):
    return _sub_batch(nn.functional.mish, mish_jvp, x, xd)


def _group_norm_t(gn: nn.GroupNorm, x: torch.Tensor, xd: torch.Tensor | None):
    return _sub_batch(gn, lambda a, b: group_norm_jvp(gn, a, b), x, xd)


class StackedLinear(nn.Module):
    """R independent ``nn.Linear(n_in, n_out)``: ``(..., R, n_in) -> (..., R, n_out)``."""

    def __init__(self, R: int, n_in: int, n_out: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(R, n_out, n_in))
        self.bias = nn.Parameter(torch.empty(R, n_out))
        for r in range(R):   # nn.Linear's initialisation, member by member
            nn.init.kaiming_uniform_(self.weight[r], a=math.sqrt(5))
            bound = 1 / math.sqrt(n_in) if n_in > 0 else 0
            nn.init.uniform_(self.bias[r], -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-2]
        xr = x.reshape(-1, *x.shape[-2:]).transpose(0, 1)                    # (R, N, in)
        y = torch.baddbmm(self.bias[:, None], xr, self.weight.transpose(1, 2))  # (R, N, out)
        return y.transpose(0, 1).reshape(*lead, self.weight.shape[0], self.weight.shape[1])


# the layers of R members (R = 1: the plain layer)
def _linear(R: int, n_in: int, n_out: int) -> nn.Module:
    return nn.Linear(n_in, n_out) if R == 1 else StackedLinear(R, n_in, n_out)


def _conv(R: int, c_in: int, c_out: int, *args, transposed: bool = False) -> nn.Module:
    return (nn.ConvTranspose1d if transposed else nn.Conv1d)(R * c_in, R * c_out, *args, groups=R)


def _member_cat(a: torch.Tensor, b: torch.Tensor, R: int) -> torch.Tensor:
    """Channel concatenation of two feature maps, member by member: (B, R Ca, L), (B, R Cb, L)."""
    if R == 1:
        return torch.cat([a, b], dim=1)
    B, _, L = a.shape
    return torch.cat([a.reshape(B, R, -1, L), b.reshape(B, R, -1, L)], dim=2).reshape(B, -1, L)


class StepEmbedding(nn.Module):
    """Sinusoidal embedding of the diffusion step, then Linear-Mish-Linear: (B, [R]) -> (B, [R], dim)."""

    def __init__(self, dim: int, R: int = 1):
        super().__init__()
        half = dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half) / max(half - 1, 1))
        self.register_buffer("freqs", freqs, persistent=False)
        self.mlp = nn.Sequential(_linear(R, 2 * half, 4 * dim), nn.Mish(), _linear(R, 4 * dim, dim))

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        arg = k.float()[..., None] * self.freqs
        return self.mlp(torch.cat([arg.sin(), arg.cos()], dim=-1))


class ConvBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish, length preserving."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int, R: int = 1):
        super().__init__(_conv(R, c_in, c_out, kernel_size, 1, kernel_size // 2),
                         nn.GroupNorm(R * n_groups, R * c_out), nn.Mish())

    def forward_jvp(self, x, xd):
        conv, gn, _ = self
        return _mish_t(*_group_norm_t(gn, *_linear_t(conv, x, xd)))


class FiLMResBlock(nn.Module):
    """Two conv blocks with FiLM conditioning between them, plus a residual path."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int, n_groups: int, R: int = 1):
        super().__init__()
        self.block1 = ConvBlock(c_in, c_out, kernel_size, n_groups, R)
        self.block2 = ConvBlock(c_out, c_out, kernel_size, n_groups, R)
        self.film = nn.Sequential(nn.Mish(), _linear(R, cond_dim, 2 * c_out))
        self.residual = _conv(R, c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.c_out, self.R = c_out, R

    def _split(self, f: torch.Tensor):
        """FiLM output ``(B, [R], 2 C)`` -> per-channel ``(scale, bias)``, each ``(B, R C, 1)``."""
        C, B = self.c_out, f.shape[0]
        return f[..., :C].reshape(B, self.R * C, 1), f[..., C:].reshape(B, self.R * C, 1)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.block1(x)
        scale, bias = self._split(self.film(cond))
        h = self.block2(scale * h + bias)
        return h + self.residual(x)

    def forward_jvp(self, x, xd, cond, cond_d):
        h, hd = self.block1.forward_jvp(x, xd)
        m, md = _mish_t(cond, cond_d)
        f, fd = _linear_t(self.film[1], m, md)
        scale, bias = self._split(f)
        g, gd = scale * h + bias, None
        if fd is not None or hd is not None:
            gd = 0
            n = (fd if fd is not None else hd).shape[0]   # tangents cover the first n samples
            if fd is not None:
                sd, bd = self._split(fd)
                gd = sd * h[:n] + bd
            if hd is not None:
                gd = gd + scale[:n] * hd
        h, hd = self.block2.forward_jvp(g, gd)
        r, rd = (x, xd) if isinstance(self.residual, nn.Identity) else _linear_t(self.residual, x, xd)
        return h + r, (hd if rd is None else hd + rd)


class ConditionalUnet1D(nn.Module):
    """``forward(tau (B, T_h, A), k (B,), cond (B, n_cond)) -> (B, T_h, A)``; ``members=R > 1``: R networks,
    ``(B, R, T_h, A), (B, R), (B, R, n_cond) -> (B, R, T_h, A)`` (see the module docstring)."""

    def __init__(self, action_dim: int, cond_dim: int, down_dims=(24, 24, 32, 32), kernel_size: int = 5,
                 n_groups: int = 8, step_embed_dim: int = 64, members: int = 1):
        super().__init__()
        R = self.R = members
        #: the constructor's arguments but ``members`` (a stack of these networks: :func:`stack_members`)
        self.arch = dict(action_dim=action_dim, cond_dim=cond_dim, down_dims=tuple(down_dims),
                         kernel_size=kernel_size, n_groups=n_groups, step_embed_dim=step_embed_dim)
        self.step_embed = StepEmbedding(step_embed_dim, R)
        cdim = step_embed_dim + cond_dim
        dims = [action_dim, *down_dims]
        pairs = list(zip(dims[:-1], dims[1:]))
        blk = lambda a, b: FiLMResBlock(a, b, cdim, kernel_size, n_groups, R)
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down.append(nn.ModuleList([blk(a, b), blk(b, b),
                                            nn.Identity() if last else _conv(R, b, b, 3, 2, 1)]))
        d = down_dims[-1]
        self.mid = nn.ModuleList([blk(d, d), blk(d, d)])
        self.up = nn.ModuleList()
        for a, b in reversed(pairs[1:]):
            self.up.append(nn.ModuleList([blk(2 * b, a), blk(a, a), _conv(R, a, a, 4, 2, 1, transposed=True)]))
        self.final = nn.Sequential(ConvBlock(down_dims[0], down_dims[0], kernel_size, n_groups, R),
                                   _conv(R, down_dims[0], action_dim, 1))

    # layout: a chunk (B, [R,] T, A) <-> channels first (B, R A, T)
    def _channels(self, t: torch.Tensor) -> torch.Tensor:
        if self.R == 1:
            return t.transpose(1, 2)
        B, R, T, A = t.shape
        return t.permute(0, 1, 3, 2).reshape(B, R * A, T)

    def _chunk(self, x: torch.Tensor) -> torch.Tensor:
        if self.R == 1:
            return x.transpose(1, 2)
        B, RA, T = x.shape
        return x.reshape(B, self.R, RA // self.R, T).permute(0, 1, 3, 2)

    def forward(self, tau: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = torch.cat([self.step_embed(k), cond], dim=-1)
        x = self._channels(tau)
        skips = []
        for r1, r2, down in self.down:
            x = r2(r1(x, c), c)
            skips.append(x)
            x = down(x)
        for r in self.mid:
            x = r(x, c)
        for r1, r2, up in self.up:
            x = _member_cat(x, skips.pop(), self.R)
            x = up(r2(r1(x, c), c))
        return self._chunk(self.final(x))

    def forward_jvp(self, tau, tau_d, k, cond, cond_d):
        """``(y, dy)``: the output and its derivative along tangents ``tau_d (n, [R,] T_h, A)`` of the
        input and ``cond_d (n, [R,] n_cond)`` of the condition (either may be None = zero). The
        tangents may cover only the first ``n <= B`` samples; then ``dy`` is ``(n, [R,] T_h, A)``."""
        R = self.R
        e = self.step_embed(k)
        c = torch.cat([e, cond], dim=-1)
        cd = None if cond_d is None else torch.cat([torch.zeros_like(e[: cond_d.shape[0]]), cond_d], dim=-1)
        x, xd = self._channels(tau), None if tau_d is None else self._channels(tau_d)
        skips = []
        for r1, r2, down in self.down:
            x, xd = r2.forward_jvp(*r1.forward_jvp(x, xd, c, cd), c, cd)
            skips.append((x, xd))
            if not isinstance(down, nn.Identity):
                x, xd = _linear_t(down, x, xd)
        for r in self.mid:
            x, xd = r.forward_jvp(x, xd, c, cd)
        for r1, r2, up in self.up:
            s, sd = skips.pop()
            if xd is not None or sd is not None:
                n = (xd if xd is not None else sd).shape[0]
                xd = _member_cat(torch.zeros_like(x[:n]) if xd is None else xd,
                                 torch.zeros_like(s[:n]) if sd is None else sd, R)
            x = _member_cat(x, s, R)
            x, xd = _linear_t(up, *r2.forward_jvp(*r1.forward_jvp(x, xd, c, cd), c, cd))
        x, xd = self.final[0].forward_jvp(x, xd)
        x, xd = _linear_t(self.final[1], x, xd)
        return self._chunk(x), None if xd is None else self._chunk(xd)


# ------------------------------------------------------- stacks of solo networks
def member_view(stacked: torch.Tensor, solo_dim: int, R: int, r: int) -> torch.Tensor:
    """Member ``r``'s block of a stacked tensor (a view) whose solo tensor has ``solo_dim`` dimensions."""
    return stacked[r] if stacked.dim() == solo_dim + 1 else stacked.chunk(R, dim=0)[r]


def stack_members(nets: list[ConditionalUnet1D]) -> ConditionalUnet1D:
    """One stacked network (``members=len(nets)``) whose member ``r`` has the weights of ``nets[r]`` (solo
    networks of one architecture)."""
    R = len(nets)
    if any(n.R != 1 or n.arch != nets[0].arch for n in nets):
        raise ValueError("stack_members needs solo networks of one architecture")
    stacked = ConditionalUnet1D(**nets[0].arch, members=R)
    states = [n.state_dict() for n in nets]
    new = {}
    for k, v in stacked.state_dict().items():
        parts = [s[k].to(v.dtype) for s in states]
        new[k] = torch.stack(parts) if v.dim() == parts[0].dim() + 1 else torch.cat(parts)
    stacked.load_state_dict(new)
    return stacked.to(next(nets[0].parameters()).device)


def member_state_dict(stacked: ConditionalUnet1D, r: int, solo: ConditionalUnet1D) -> dict:
    """Member ``r``'s weights of a stacked network as a state dict of the solo network ``solo`` (for shapes)."""
    ref = solo.state_dict()
    return {k: member_view(v, ref[k].dim(), stacked.R, r).clone() for k, v in stacked.state_dict().items()}


def compile_unet(net: ConditionalUnet1D) -> None:
    """Compile ``net.forward`` and ``net.forward_jvp`` in place (:func:`sdp_cli.policy.compiling.compiled`:
    inductor, the shared cache); parameters and state dict stay the network's. The hand-written tangent pass traces without graph
    breaks (its custom autograd functions included)."""
    net.forward = compiled(net.forward)
    net.forward_jvp = compiled(net.forward_jvp)

"""R independent U-Nets in one module (issue "Many runs at once"): the paper's U-Net is tiny, so a training
step is mostly per-op overhead; R runs stacked as groups of one network cost little more than one.

:class:`StackedUnet1D` holds R copies of :class:`~sdp_cli.policy.unet.ConditionalUnet1D` (same
architecture, independent weights) as

- grouped convolutions (``groups=R``: member ``r``'s channels are the block ``[r C, (r + 1) C)``),
- GroupNorm over ``R x n_groups`` groups (a member's groups never mix with another's),
- batched linear layers (:class:`StackedLinear`, weights ``(R, out, in)``) for the step embedding and FiLM,

so member ``r`` computes exactly what a solo network with its weights computes (to float32 rounding: the grouped
kernels sum in another order). ``forward(tau (B, R, T_h, A), k (B, R), cond (B, R, n_cond)) -> (B, R, T_h, A)``:
the batch axis is shared (members with fewer samples are padded by the caller, and their padded rows masked out of
their losses), everything else is per member. :meth:`StackedUnet1D.forward_jvp` is the solo network's hand-written
tangent propagation, stacked the same way. :meth:`StackedUnet1D.from_members` builds one from R solo networks and
:meth:`StackedUnet1D.member_state_dict` gives member ``r``'s weights back as a solo state dict (a stacked run's
checkpoint is a solo one).
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from sdp_cli.policy.unet import (ConditionalUnet1D, ConvBlock, FiLMResBlock, StepEmbedding, _group_norm_t,
                                 _linear_t, _mish_t)


class StackedLinear(nn.Module):
    """R independent ``nn.Linear(n_in, n_out)``: ``(..., R, n_in) -> (..., R, n_out)``."""

    def __init__(self, R: int, n_in: int, n_out: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(R, n_out, n_in))
        self.bias = nn.Parameter(torch.empty(R, n_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-2]
        xr = x.reshape(-1, *x.shape[-2:]).transpose(0, 1)                    # (R, N, in)
        y = torch.baddbmm(self.bias[:, None], xr, self.weight.transpose(1, 2))  # (R, N, out)
        return y.transpose(0, 1).reshape(*lead, self.weight.shape[0], self.weight.shape[1])


def _stack_layer(layer: nn.Module, R: int) -> nn.Module:
    """The R-member version of one solo layer (weights left to :meth:`StackedUnet1D.load_members`)."""
    if isinstance(layer, nn.Linear):
        return StackedLinear(R, layer.in_features, layer.out_features)
    if isinstance(layer, nn.Conv1d):
        return nn.Conv1d(R * layer.in_channels, R * layer.out_channels, layer.kernel_size, layer.stride,
                         layer.padding, groups=R, bias=layer.bias is not None)
    if isinstance(layer, nn.ConvTranspose1d):
        return nn.ConvTranspose1d(R * layer.in_channels, R * layer.out_channels, layer.kernel_size, layer.stride,
                                  layer.padding, groups=R, bias=layer.bias is not None)
    if isinstance(layer, nn.GroupNorm):
        return nn.GroupNorm(R * layer.num_groups, R * layer.num_channels, layer.eps, layer.affine)
    return layer


def _stack_module(module: nn.Module, R: int) -> nn.Module:
    """A deep copy of ``module`` with every layer replaced by its R-member version (same attribute names)."""
    out = copy.deepcopy(module)
    for name, child in list(out.named_children()):
        new = _stack_layer(child, R)
        setattr(out, name, new if new is not child else _stack_module(child, R))
    return out


def _per_member_cat(a: torch.Tensor, b: torch.Tensor, R: int) -> torch.Tensor:
    """Channel concatenation of two stacked feature maps, member by member: (B, R Ca, L), (B, R Cb, L)."""
    B, _, L = a.shape
    return torch.cat([a.reshape(B, R, -1, L), b.reshape(B, R, -1, L)], dim=2).reshape(B, -1, L)


class StackedUnet1D(nn.Module):
    """R U-Nets of one architecture (see the module docstring)."""

    def __init__(self, R: int, action_dim: int, cond_dim: int, down_dims=(24, 24, 32, 32), kernel_size: int = 5,
                 n_groups: int = 8, step_embed_dim: int = 64):
        super().__init__()
        self.R = R
        solo = ConditionalUnet1D(action_dim, cond_dim, down_dims, kernel_size, n_groups, step_embed_dim)
        self.net = _stack_module(solo, R)
        self._solo_shapes = {k: tuple(v.shape) for k, v in solo.state_dict().items()}

    # ------------------------------------------------------------------ members
    @classmethod
    def from_members(cls, nets: list[ConditionalUnet1D], **arch) -> "StackedUnet1D":
        stacked = cls(len(nets), **arch)
        stacked.load_members([n.state_dict() for n in nets])
        return stacked

    def load_members(self, states: list[dict]) -> None:
        """Member ``r`` takes solo state dict ``states[r]``."""
        own = self.net.state_dict()
        new = {}
        for k, v in own.items():
            parts = [s[k].to(v.dtype) for s in states]
            new[k] = torch.stack(parts) if v.dim() == len(self._solo_shapes[k]) + 1 else torch.cat(parts)
        self.net.load_state_dict(new)

    def member_state_dict(self, r: int) -> dict:
        """Member ``r``'s weights as a solo :class:`ConditionalUnet1D` state dict."""
        out = {}
        for k, v in self.net.state_dict().items():
            out[k] = (v[r] if v.dim() == len(self._solo_shapes[k]) + 1 else v.chunk(self.R, dim=0)[r]).clone()
        return out

    # ------------------------------------------------------------------ blocks
    def _block(self, blk: ConvBlock, x):
        conv, gn, act = blk
        return act(gn(conv(x)))

    def _res(self, blk: FiLMResBlock, x, c):
        B, R = x.shape[0], self.R
        h = self._block(blk.block1, x)
        f = blk.film[1](nn.functional.mish(c))                      # (B, R, 2 C)
        C = f.shape[-1] // 2
        scale, bias = f[..., :C].reshape(B, R * C, 1), f[..., C:].reshape(B, R * C, 1)
        h = self._block(blk.block2, scale * h + bias)
        return h + (x if isinstance(blk.residual, nn.Identity) else blk.residual(x))

    def _embed(self, k: torch.Tensor) -> torch.Tensor:
        emb: StepEmbedding = self.net.step_embed
        arg = k.float()[..., None] * emb.freqs                        # (B, R, half)
        lin1, _, lin2 = emb.mlp
        return lin2(nn.functional.mish(lin1(torch.cat([arg.sin(), arg.cos()], dim=-1))))

    def forward(self, tau: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """``tau (B, R, T_h, A)``, ``k (B, R)``, ``cond (B, R, n_cond)`` -> ``(B, R, T_h, A)``."""
        B, R, T, A = tau.shape
        net = self.net
        c = torch.cat([self._embed(k), cond], dim=-1)
        x = tau.permute(0, 1, 3, 2).reshape(B, R * A, T)
        skips = []
        for r1, r2, down in net.down:
            x = self._res(r2, self._res(r1, x, c), c)
            skips.append(x)
            x = down(x)
        for r in net.mid:
            x = self._res(r, x, c)
        for r1, r2, up in net.up:
            x = _per_member_cat(x, skips.pop(), R)
            x = up(self._res(r2, self._res(r1, x, c), c))
        x = net.final[1](self._block(net.final[0], x))
        return x.reshape(B, R, A, T).permute(0, 1, 3, 2)

    # ------------------------------------------------------------------ tangents
    def _block_t(self, blk: ConvBlock, x, xd):
        conv, gn, _ = blk
        return _mish_t(*_group_norm_t(gn, *_linear_t(conv, x, xd)))

    def _res_t(self, blk: FiLMResBlock, x, xd, c, cd):
        R = self.R
        h, hd = self._block_t(blk.block1, x, xd)
        m, md = _mish_t(c, cd)
        f, fd = _linear_t(blk.film[1], m, md)
        C = f.shape[-1] // 2
        split = lambda t: (t[..., :C].reshape(t.shape[0], R * C, 1), t[..., C:].reshape(t.shape[0], R * C, 1))
        scale, bias = split(f)
        g, gd = scale * h + bias, None
        if fd is not None or hd is not None:
            gd = 0
            n = (fd if fd is not None else hd).shape[0]
            if fd is not None:
                sd, bd = split(fd)
                gd = sd * h[:n] + bd
            if hd is not None:
                gd = gd + scale[:n] * hd
        h, hd = self._block_t(blk.block2, g, gd)
        r, rd = (x, xd) if isinstance(blk.residual, nn.Identity) else _linear_t(blk.residual, x, xd)
        return h + r, (hd if rd is None else hd + rd)

    def forward_jvp(self, tau, tau_d, k, cond, cond_d):
        """``(y, dy)`` along tangents ``tau_d (n, R, T_h, A)`` and ``cond_d (n, R, n_cond)`` (either None = zero)
        of the first ``n <= B`` samples; as :meth:`ConditionalUnet1D.forward_jvp`, member by member."""
        B, R, T, A = tau.shape
        net = self.net
        e = self._embed(k)
        c = torch.cat([e, cond], dim=-1)
        cd = None if cond_d is None else torch.cat([torch.zeros_like(e[: cond_d.shape[0]]), cond_d], dim=-1)
        flat = lambda t: t.permute(0, 1, 3, 2).reshape(t.shape[0], R * A, T)
        x, xd = flat(tau), None if tau_d is None else flat(tau_d)
        skips = []
        for r1, r2, down in net.down:
            x, xd = self._res_t(r2, *self._res_t(r1, x, xd, c, cd), c, cd)
            skips.append((x, xd))
            if not isinstance(down, nn.Identity):
                x, xd = _linear_t(down, x, xd)
        for r in net.mid:
            x, xd = self._res_t(r, x, xd, c, cd)
        for r1, r2, up in net.up:
            s, sd = skips.pop()
            if xd is not None or sd is not None:
                n = (xd if xd is not None else sd).shape[0]
                xd = _per_member_cat(torch.zeros_like(x[:n]) if xd is None else xd,
                                     torch.zeros_like(s[:n]) if sd is None else sd, R)
            x = _per_member_cat(x, s, R)
            x, xd = _linear_t(up, *self._res_t(r2, *self._res_t(r1, x, xd, c, cd), c, cd))
        x, xd = self._block_t(net.final[0], x, xd)
        x, xd = _linear_t(net.final[1], x, xd)
        back = lambda t: t.reshape(t.shape[0], R, A, T).permute(0, 1, 3, 2)
        return back(x), None if xd is None else back(xd)

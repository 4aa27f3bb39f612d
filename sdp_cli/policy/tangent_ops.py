"""Fused primal + tangent ops with closed-form backward passes (used by the U-Net's JVP).

Each op maps ``(x, xd)`` to ``(y, yd)`` with ``yd = (dy/dx) xd`` and implements its own
``backward`` (gradients of both outputs w.r.t. ``x``, ``xd`` and the parameters), which
saves most of the elementwise passes autograd would record for the same formulas.
Checked against autograd by ``torch.autograd.gradcheck`` in ``tests/test_policy_model.py``.

Mish: ``m(x) = x tanh(softplus(x))``, with ``t = tanh(softplus(x))`` and ``s = sigmoid(x)``:
``m' = t + x s (1 - t^2)``, ``m'' = s (1 - t^2) (2 + x (1 - s) - 2 x t s)``.

GroupNorm over groups of ``n`` elements: ``u = x - mean(x)``, ``r = (mean(u^2) + eps)^(-1/2)``,
``xhat = u r``, ``y = gamma xhat + beta``;
tangent ``xhat_d = r (xd_c - xhat mean(xhat xd))`` with ``xd_c = xd - mean(xd)``.
"""

from __future__ import annotations

import torch


class MishJVP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, xd):
        s = torch.sigmoid(x)
        t = torch.tanh(torch.nn.functional.softplus(x))
        one_t2 = 1 - t * t
        d1 = t + x * s * one_t2
        ctx.save_for_backward(x, xd, s, t, one_t2, d1)
        return x * t, xd * d1

    @staticmethod
    def backward(ctx, gy, gyd):
        x, xd, s, t, one_t2, d1 = ctx.saved_tensors
        d2 = s * one_t2 * (2 + x * (1 - s) - 2 * x * t * s)
        gx = gy * d1 + gyd * d2 * xd
        gxd = gyd * d1
        return gx, gxd


def mish_jvp(x, xd):
    return MishJVP.apply(x, xd)


class GroupNormJVP(torch.autograd.Function):
    """Primal by ``native_group_norm``; the tangent ``xhat_d`` is exactly the GroupNorm
    input-gradient map applied to ``xd`` (``native_group_norm_backward`` with unit weight),
    so both forward parts and the two GroupNorm-shaped backward parts are fused kernels;
    only the second-order terms (tangent path w.r.t. ``x``) are composed by hand."""

    @staticmethod
    def forward(ctx, x, xd, weight, bias, groups: int, eps: float):
        B, C, L = x.shape
        y, mean, rstd = torch.native_group_norm(x, weight, bias, B, C, L, groups, eps)
        xhat_d = torch.ops.aten.native_group_norm_backward(xd, x, mean, rstd, None, B, C, L, groups,
                                                            [True, False, False])[0]
        ctx.save_for_backward(x, xd, mean, rstd, weight, xhat_d)
        ctx.groups = groups
        return y, xhat_d * weight[:, None]

    @staticmethod
    def backward(ctx, gy, gyd):
        x, xd, mean, rstd, weight, xhat_d = ctx.saved_tensors
        B, C, L = x.shape
        G = ctx.groups
        gy, gyd = gy.contiguous(), gyd.contiguous()
        # y path (standard GroupNorm backward) and the tangent path w.r.t. xd (same linear map)
        gx, gw, gb = torch.ops.aten.native_group_norm_backward(gy, x, mean, rstd, weight, B, C, L, G,
                                                                [True, True, True])
        gxd = torch.ops.aten.native_group_norm_backward(gyd, x, mean, rstd, weight, B, C, L, G,
                                                         [True, False, False])[0]
        gw = gw + (gyd * xhat_d).sum((0, 2))
        # tangent path w.r.t. x: xhat_d = r xd_c - u r^3 b, b = mean(u xd); its gradient is
        # alpha gq + beta u + gamma xd_c + delta with per-group scalars (reductions by bmm)
        r = rstd[:, :, None]
        n = x.numel() // (B * G)
        u = x.reshape(B, G, -1) - mean[:, :, None]
        xdg = xd.reshape(B, G, -1)
        xdc = xdg - xdg.mean(-1, keepdim=True)
        gq = (gyd * weight[:, None]).reshape(B, G, -1)
        dot = lambda a, c: torch.einsum("bgn,bgn->bg", a, c)[:, :, None] / n
        b = dot(u, xdc)
        m_gq_u, m_gq_xdc, m_gq = dot(gq, u), dot(gq, xdc), gq.mean(-1, keepdim=True)
        r3 = r * r * r
        alpha = -r3 * b
        beta = -r3 * (m_gq_xdc - 3 * r * r * b * m_gq_u)
        gamma = -r3 * m_gq_u
        extra = torch.addcmul(-alpha * m_gq, alpha, gq)
        extra.addcmul_(beta, u).addcmul_(gamma, xdc)
        return gx + extra.reshape(B, C, L), gxd, gw, gb, None, None


def group_norm_jvp(gn: torch.nn.GroupNorm, x, xd):
    return GroupNormJVP.apply(x, xd, gn.weight, gn.bias, gn.num_groups, gn.eps)

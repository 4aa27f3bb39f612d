"""Stochastic Sobolev terms (eqs. (4) and (6) of the paper).

A model output ``y = f(delta) (B, *out)`` depends on a normalized state perturbation
``delta (B, d_in)`` (evaluated at ``delta = 0``); the target Jacobian is ``J (B, *out, d_in)``.
With ``M = J - dy/d delta`` per sample and ``d_out = prod(out)``:

- :func:`sobolev_output_projection` (eq. (6), reverse over reverse): ``||v^T M||^2`` with
  ``v`` uniform on the unit sphere of the output space, ``E_v = ||M||_F^2 / d_out``;
- :func:`sobolev_input_projection` (forward mode, cheaper here because ``d_in << d_out``):
  ``(d_in / d_out) ||M w||^2`` with ``w`` uniform on the unit sphere of the input space,
  ``E_w = ||M||_F^2 / d_out`` too, so ``alpha_Sobolev`` keeps its meaning.

Both average over ``n_proj`` directions and return ``(y, term (B,))``; ``y`` is the primal
output at ``delta = 0`` (shared with the regression term, no recomputation). The
regression term is the per-element mean squared error, ``||Delta y||^2 / d_out``,
which is consistent with these scalings: ``E[loss] = (||Delta y||^2 + alpha ||M||_F^2) / d_out``.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch.func import jvp


def random_unit(shape: tuple, generator: torch.Generator | None = None, device=None,
                dtype=None) -> torch.Tensor:
    """Vectors uniform on the unit sphere over the trailing dims of ``shape[1:]`` (per row); drawn on
    the generator's device (training uses a CPU generator, so a seed means the same on a GPU)."""
    v = torch.randn(shape, generator=generator, device=generator.device if generator is not None else device,
                    dtype=dtype).to(device)
    flat = v.reshape(shape[0], -1)
    return (flat / flat.norm(dim=1, keepdim=True).clamp_min(1e-12)).reshape(shape)


def sobolev_output_projection(f: Callable[[torch.Tensor], torch.Tensor], d_in: int, J: torch.Tensor,
                              n_proj: int = 1, generator: torch.Generator | None = None):
    """``(y, mean_i ||v_i^T J - d(v_i^T f)/d delta||^2)`` by double backward. J (B, *out, d_in)."""
    B = J.shape[0]
    delta = torch.zeros(B, d_in, device=J.device, dtype=J.dtype, requires_grad=True)
    with torch.enable_grad():
        y = f(delta)
        term = torch.zeros(B, device=J.device, dtype=J.dtype)
        for i in range(n_proj):
            v = random_unit(y.shape, generator, J.device, J.dtype)
            (g,) = torch.autograd.grad((v * y).sum(), delta, create_graph=True)
            target = torch.einsum("bo,boi->bi", v.reshape(B, -1), J.reshape(B, -1, d_in))
            term = term + ((target - g) ** 2).sum(-1)
    return y, term / n_proj


def sobolev_input_projection(f: Callable[[torch.Tensor], torch.Tensor], d_in: int, J: torch.Tensor,
                             n_proj: int = 1, generator: torch.Generator | None = None,
                             f_jvp: Callable[[torch.Tensor], tuple] | None = None):
    """``(y, mean_i (d_in/d_out) ||J w_i - df/d delta w_i||^2)`` by forward-mode JVPs.

    ``f_jvp(w) -> (f(0), df/d delta (0) w)`` replaces ``torch.func.jvp(f, ...)`` when given
    (e.g. the U-Net's hand-written tangent propagation)."""
    B = J.shape[0]
    delta = torch.zeros(B, d_in, device=J.device, dtype=J.dtype)
    Jf = J.reshape(B, -1, d_in)
    d_out = Jf.shape[1]
    term = torch.zeros(B, device=J.device, dtype=J.dtype)
    y = None
    for _ in range(n_proj):
        w = random_unit((B, d_in), generator, J.device, J.dtype)
        y, ydot = f_jvp(w) if f_jvp is not None else jvp(f, (delta,), (w,))
        target = torch.einsum("boi,bi->bo", Jf, w)
        term = term + ((target - ydot.reshape(B, -1)) ** 2).sum(-1)
    return y, term * (d_in / d_out) / n_proj


def sobolev_term(mode: str, f, d_in: int, J: torch.Tensor, n_proj: int = 1, generator=None, f_jvp=None):
    """Dispatch on ``mode``: "vjp" (output projection, eq. (6)) or "jvp" (input projection)."""
    if mode == "vjp":
        return sobolev_output_projection(f, d_in, J, n_proj, generator)
    if mode == "jvp":
        return sobolev_input_projection(f, d_in, J, n_proj, generator, f_jvp)
    raise ValueError(f"unknown Sobolev mode {mode!r}")


def capped_weights(J: torch.Tensor, quantile: float) -> torch.Tensor:
    """Per-sample Sobolev weights ``min(1, (c / ||J_s||_F)^2)`` with ``c`` the ``quantile`` of the
    norms ``||J_s||_F`` over the samples (J (N, ..., d_in)): the squared error of a sample whose
    target Jacobian is larger than ``c`` counts as if its Jacobian had norm ``c``, so a few chunks
    with huge gains (e.g. an unstable closed loop) cannot dominate the term. (N,)"""
    norms = J.reshape(J.shape[0], -1).norm(dim=1)
    c = torch.quantile(norms.double(), quantile).to(norms.dtype)
    return (c / norms.clamp_min(1e-12)).clamp(max=1.0) ** 2


def balance_scale(target: torch.Tensor, J: torch.Tensor) -> float:
    """``rho = mean(target^2) / mean_s(||J_s||_F^2 / d_out)``: the factor on the Sobolev term under
    which ``alpha_Sobolev = 1`` weighs the two terms of eqs. (4)/(6) equally on this dataset.

    Principle: alpha is the relative weight of the first-order term, so the scale of the state
    (whose units are arbitrary: radians or metres, min-max range or standard deviation) must
    not change its meaning. With ``rho``, the constant predictor at the centre of the action
    range (zero in normalized units) pays the same expected regression loss and Sobolev loss
    at alpha = 1; both terms are then measured relative to the size of their targets.
    Equivalently, the state tangent is rescaled by ``sqrt(rho)`` in every coordinate.
    ``target (N, *out)``, ``J (N, *out, d_in)`` in normalized units; 1.0 if ``J`` is zero.
    """
    d_out = target[0].numel()
    num = float((target.double() ** 2).mean())
    den = float((J.double() ** 2).reshape(J.shape[0], -1).sum(1).mean()) / d_out
    if not (den > 1e-12 and num > 0):
        return 1.0
    return num / den

"""Sobolev terms against brute-force Jacobians; zero loss on an exact linear model."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from sdp_cli.losses.sobolev import random_unit, sobolev_input_projection, sobolev_output_projection

B, D_IN, OUT = 5, 3, (4, 2)


@pytest.fixture(autouse=True)
def _double():
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def tiny_net():
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(D_IN + 2, 16), nn.Tanh(), nn.Linear(16, 8))


def model(net, ctx):
    """f(delta) = net(ctx + P delta): the structure of the policy's linearized input."""
    P = torch.linspace(-1, 1, (D_IN + 2) * D_IN).reshape(D_IN + 2, D_IN)
    return lambda delta: net(ctx + delta @ P.T).reshape(B, *OUT)


def assert_same_grads(a, b, net):
    params = list(net.parameters())
    g1 = torch.autograd.grad(a, params, allow_unused=True, retain_graph=True)
    g2 = torch.autograd.grad(b, params, allow_unused=True, retain_graph=True)
    assert any(g is not None for g in g1)
    for p, x, y in zip(params, g1, g2):
        torch.testing.assert_close(torch.zeros_like(p) if x is None else x, torch.zeros_like(p) if y is None else y)


def brute_force_jacobian(f):
    """Full per-sample Jacobian by autograd: (B, *OUT, D_IN)."""
    J = torch.autograd.functional.jacobian(f, torch.zeros(B, D_IN), create_graph=True)  # (B,*OUT,B,D_IN)
    idx = torch.arange(B)
    return J.reshape(B, -1, B, D_IN)[idx, :, idx].reshape(B, *OUT, D_IN)


def test_output_projection_matches_brute_force():
    net = tiny_net()
    ctx = torch.randn(B, D_IN + 2, generator=torch.Generator().manual_seed(1))
    f = model(net, ctx)
    J_true = torch.randn(B, *OUT, D_IN, generator=torch.Generator().manual_seed(2))
    y, term = sobolev_output_projection(f, D_IN, J_true, n_proj=1, generator=torch.Generator().manual_seed(3))
    v = random_unit((B, *OUT), torch.Generator().manual_seed(3))
    M = (J_true - brute_force_jacobian(f)).reshape(B, -1, D_IN)
    expected = (torch.einsum("bo,boi->bi", v.reshape(B, -1), M) ** 2).sum(-1)
    torch.testing.assert_close(term, expected)
    torch.testing.assert_close(y, f(torch.zeros(B, D_IN)))
    # gradients w.r.t. the parameters agree too (this is what training uses)
    assert_same_grads(term.sum(), expected.sum(), net)


def test_input_projection_matches_brute_force():
    net = tiny_net()
    ctx = torch.randn(B, D_IN + 2, generator=torch.Generator().manual_seed(1))
    f = model(net, ctx)
    J_true = torch.randn(B, *OUT, D_IN, generator=torch.Generator().manual_seed(2))
    _, term = sobolev_input_projection(f, D_IN, J_true, n_proj=1, generator=torch.Generator().manual_seed(3))
    w = random_unit((B, D_IN), torch.Generator().manual_seed(3))
    M = (J_true - brute_force_jacobian(f)).reshape(B, -1, D_IN)
    d_out = M.shape[1]
    expected = (torch.einsum("boi,bi->bo", M, w) ** 2).sum(-1) * D_IN / d_out
    torch.testing.assert_close(term, expected)
    assert_same_grads(term.sum(), expected.sum(), net)


def test_both_estimators_have_the_same_expectation():
    """E_v ||v^T M||^2 = E_w (d_in/d_out) ||M w||^2 = ||M||_F^2 / d_out (alpha keeps its meaning)."""
    M = torch.randn(B, *OUT, D_IN, generator=torch.Generator().manual_seed(4))
    zero_f = lambda delta: torch.zeros(B, *OUT) + 0 * delta.sum()
    g = torch.Generator().manual_seed(5)
    _, t_out = sobolev_output_projection(zero_f, D_IN, M, n_proj=600, generator=g)
    _, t_in = sobolev_input_projection(zero_f, D_IN, M, n_proj=600, generator=g)
    exact = (M.reshape(B, -1) ** 2).sum(-1) / M[0, ..., 0].numel()
    torch.testing.assert_close(t_out, exact, rtol=0.15, atol=0)
    torch.testing.assert_close(t_in, exact, rtol=0.15, atol=0)


@pytest.mark.parametrize("fn", [sobolev_output_projection, sobolev_input_projection])
def test_zero_loss_on_exact_linear_model(fn):
    """A network reproducing y = W (ctx + P delta) + b and its Jacobian exactly has a zero term."""
    lin = nn.Linear(D_IN + 2, 8)
    ctx = torch.randn(B, D_IN + 2)
    f = model(lin, ctx)
    P = torch.linspace(-1, 1, (D_IN + 2) * D_IN).reshape(D_IN + 2, D_IN)
    J_true = (lin.weight.detach() @ P).reshape(*OUT, D_IN).expand(B, *OUT, D_IN)
    y, term = fn(f, D_IN, J_true, n_proj=3, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(term, torch.zeros(B), atol=1e-20, rtol=0)
    grads = torch.autograd.grad(term.sum(), list(lin.parameters()), allow_unused=True)
    assert all(g is None or g.abs().max() < 1e-12 for g in grads)
    # and a wrong Jacobian gives a positive term
    _, bad = fn(f, D_IN, J_true + 0.1, n_proj=1, generator=torch.Generator().manual_seed(0))
    assert torch.all(bad > 0)


def test_capped_weights_bound_each_samples_sobolev_scale():
    from sdp_cli.losses.sobolev import capped_weights

    scales = torch.tensor([1.0, 2.0, 3.0, 4.0, 100.0])
    J = scales[:, None, None] * random_unit((5, 4, 3), torch.Generator().manual_seed(0))  # ||J_s||_F = scale
    w = capped_weights(J, 0.5)                       # cap = median norm = 3
    torch.testing.assert_close(w[:3], torch.ones(3))
    # above the cap, weight x ||J||^2 = cap^2: the outlier counts like a sample of norm 3
    torch.testing.assert_close(w[3:] * scales[3:] ** 2, torch.full((2,), 9.0))
    torch.testing.assert_close(capped_weights(J, 1.0), torch.ones(5))   # quantile 1: no capping


def test_sobolev_cap_is_validated():
    from sdp_cli.errors import SdpError
    from sdp_cli.policy.config import TrainConfig

    with pytest.raises(SdpError, match="sobolev_cap must be a finite number in \\(0, 1\\], got 1.5"):
        TrainConfig.of(method="sdp", sobolev_cap=1.5)
    with pytest.raises(SdpError, match="sobolev_cap applies to Sobolev diffusion methods \\(sdp\\), not 'dp'"):
        TrainConfig.of(method="dp", sobolev_cap=0.9)

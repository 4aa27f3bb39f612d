"""R U-Nets stacked in one module (sdp_cli.policy.unet, members=R): each member computes what a solo network with
its weights computes (forward, the hand-written JVP, and the gradients of both), and its weights come back as a
solo state dict. Checked in float64, where the grouped kernels' other summation order is invisible."""

from __future__ import annotations

import torch

from sdp_cli.policy.unet import ConditionalUnet1D, member_state_dict, stack_members

R, A, NC, T, B = 3, 2, 7, 16, 5
ARCH = dict(action_dim=A, cond_dim=NC, down_dims=(8, 16), kernel_size=5, n_groups=4, step_embed_dim=8)


def _members():
    torch.manual_seed(0)
    nets = [ConditionalUnet1D(**ARCH).double() for _ in range(R)]
    return nets, stack_members(nets).double()


def _inputs(n=3):
    g = torch.Generator().manual_seed(1)
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)   # noqa: E731
    return (r(B, R, T, A), torch.randint(0, 5, (B, R), generator=g), r(B, R, NC), r(n, R, T, A), r(n, R, NC))


def test_each_member_is_a_solo_network_forward_jvp_and_gradients():
    nets, st = _members()
    tau, k, cond, tau_d, cond_d = _inputs()
    y = st(tau, k, cond)
    ys, yds = st.forward_jvp(tau, tau_d, k, cond, cond_d)
    ((ys ** 2).sum() + (yds ** 2).sum() + (y ** 3).sum()).backward()
    grads = dict(st.named_parameters())
    for r, net in enumerate(nets):
        y1 = net(tau[:, r], k[:, r], cond[:, r])
        torch.testing.assert_close(y[:, r], y1, rtol=1e-12, atol=1e-12)
        y2, yd2 = net.forward_jvp(tau[:, r], tau_d[:, r], k[:, r], cond[:, r], cond_d[:, r])
        torch.testing.assert_close(ys[:, r], y2, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(yds[:, r], yd2, rtol=1e-12, atol=1e-12)
        ((y2 ** 2).sum() + (yd2 ** 2).sum() + (y1 ** 3).sum()).backward()
        for name, p in net.named_parameters():
            g = grads[name].grad
            mine = g[r] if g.dim() == p.dim() + 1 else g.chunk(R, dim=0)[r]
            torch.testing.assert_close(mine, p.grad, rtol=1e-10, atol=1e-12, msg=name)


def test_members_do_not_see_each_other_and_weights_round_trip():
    nets, st = _members()
    tau, k, cond, tau_d, cond_d = _inputs()
    y = st(tau, k, cond)
    tau2 = tau.clone()
    tau2[:, 1] += 1.0                      # another input for member 1 only
    y2 = st(tau2, k, cond)
    assert torch.equal(y[:, 0], y2[:, 0]) and torch.equal(y[:, 2], y2[:, 2]) and not torch.equal(y[:, 1], y2[:, 1])
    for r, net in enumerate(nets):
        sd = member_state_dict(st, r, net)
        assert sd.keys() == net.state_dict().keys()
        assert all(torch.equal(sd[key], v) for key, v in net.state_dict().items())
    fresh = ConditionalUnet1D(**ARCH).double()
    fresh.load_state_dict(member_state_dict(st, 2, fresh))
    torch.testing.assert_close(fresh(tau[:, 2], k[:, 2], cond[:, 2]), y[:, 2], rtol=1e-12, atol=1e-12)


def test_tangents_of_the_first_n_samples_only():
    """The Sobolev term may use the first n < B samples (sobolev_fraction): the same in the stack."""
    nets, st = _members()
    tau, k, cond, tau_d, cond_d = _inputs(n=2)
    ys, yds = st.forward_jvp(tau, tau_d, k, cond, cond_d)
    assert yds.shape == (2, R, T, A)
    for r, net in enumerate(nets):
        y2, yd2 = net.forward_jvp(tau[:, r], tau_d[:, r], k[:, r], cond[:, r], cond_d[:, r])
        torch.testing.assert_close(yds[:, r], yd2, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ys[:, r], y2, rtol=1e-12, atol=1e-12)

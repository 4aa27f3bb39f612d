"""U-Net size and shapes, hand-written tangent propagation vs torch.func.jvp, DDPM details."""

from __future__ import annotations

import pytest
import torch
from torch.func import jvp

from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.diffusion import DiffusionUnetPolicy, make_scheduler
from sdp_cli.policy.unet import ConditionalUnet1D


def make_policy(cfg, A, n_obs, n_xi, ndx):
    """The diffusion policy object with these sizes."""
    return DiffusionUnetPolicy(cfg, {"n_action": A, "n_obs": n_obs, "n_xi": n_xi, "ndx": ndx})


def test_default_unet_size_and_shapes():
    net = ConditionalUnet1D(action_dim=1, cond_dim=4 + 2)   # pendulum: xi (2) + o = (x (2), u_prev (1))... + 1
    n = sum(p.numel() for p in net.parameters())
    assert 200_000 < n < 350_000     # "about 300k parameters" with hidden dims [24, 24, 32, 32]
    y = net(torch.randn(3, 32, 1), torch.tensor([0, 2, 4]), torch.randn(3, 6))
    assert y.shape == (3, 32, 1)


@pytest.mark.parametrize("with_tau_tangent", [False, True])
def test_forward_jvp_matches_torch_func_jvp(with_tau_tangent):
    torch.manual_seed(0)
    net = ConditionalUnet1D(action_dim=2, cond_dim=5, down_dims=(8, 16, 16), n_groups=4, step_embed_dim=8).double()
    B = 4
    tau, cond = torch.randn(B, 16, 2, dtype=torch.float64), torch.randn(B, 5, dtype=torch.float64)
    k = torch.tensor([0, 1, 3, 4])
    tau_d = torch.randn_like(tau) if with_tau_tangent else None
    cond_d = torch.randn_like(cond)
    y, yd = net.forward_jvp(tau, tau_d, k, cond, cond_d)
    y_ref, yd_ref = jvp(lambda t, c: net(t, k, c), (tau, cond),
                        (tau_d if tau_d is not None else torch.zeros_like(tau), cond_d))
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(yd, yd_ref)
    # reverse-mode through the tangent gives the same parameter gradients as reverse-over-forward
    g1 = torch.autograd.grad((yd ** 2).sum(), list(net.parameters()), allow_unused=True)
    g2 = torch.autograd.grad((yd_ref ** 2).sum(), list(net.parameters()), allow_unused=True)
    for p, a, b in zip(net.parameters(), g1, g2):
        torch.testing.assert_close(torch.zeros_like(p) if a is None else a, torch.zeros_like(p) if b is None else b)


def _batch(B=6, T_h=8, A=1, n_o=3, ndx=2, state=False):
    g = torch.Generator().manual_seed(1)
    b = {"tau0": torch.rand(B, T_h, A, generator=g) * 2 - 1, "obs": torch.randn(B, 1, n_o, generator=g),
         "obs_jac": torch.randn(B, 1, n_o, ndx, generator=g), "xi": torch.randn(B, 2, generator=g),
         "jac": torch.randn(B, T_h, A, ndx, generator=g)}
    b["a_hist"] = b["tau0"][:, :1]
    if state:
        b["a_hist_jac"] = b["jac"][:, :1]
    return b


@pytest.mark.parametrize("state,path", [(False, "cond"), (True, "cond"), (False, "total"), (True, "total")])
def test_jvp_and_autograd_paths_give_the_same_sdp_loss(state, path):
    """The hand-written tangent and torch.func.jvp give the same loss and gradients (same RNG draws)."""
    cfg = TrainConfig.of(method="sdp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, sobolev_mode="jvp",
                      sobolev_path=path)
    A = 2 if state else 1
    net = make_policy(cfg, A, 3, 2, 2)
    batch = _batch(A=A, state=state)
    l1, p1 = net.compute_loss(batch, torch.Generator().manual_seed(0))
    # the same draws, the tangent by torch.func.jvp of the network as a function of the state perturbation
    d = net.draw(batch, torch.Generator().manual_seed(0))
    (w, _, _), = d["projections"]
    k, rest = d["k"], d["x"][:, 1:]
    rest_jac = net._rest_jac(batch, k)

    def f(delta):
        o = batch["obs"] + torch.einsum("btoi,bi->bto", batch["obs_jac"], delta)
        a = batch["a_hist"] + (torch.einsum("btai,bi->bta", batch["a_hist_jac"], delta) if state else 0)
        r = rest if rest_jac is None else rest + torch.einsum("btai,bi->bta", rest_jac, delta)
        return net(torch.cat([a, r], dim=1), k, batch["xi"], o)

    y, yd = jvp(f, (torch.zeros(6, 2),), (w,))
    l2, p2 = net.loss_from(d, y, [yd])
    torch.testing.assert_close(l1, l2, rtol=1e-5, atol=1e-6)
    assert p1["sobolev"] > 0


def test_total_path_is_the_derivative_through_the_noisy_chunk():
    """sobolev_path "total": both derivative paths the loss uses (autograd ``f`` of the vjp mode and the
    hand-written tangents of the jvp mode's :meth:`draw`) equal the brute-force Jacobian of the network output
    w.r.t. delta with tau_k(delta) = sqrt(alpha_bar_k) (tau_0 + J delta) + sqrt(1 - alpha_bar_k) eps; "cond"
    differs."""
    import sdp_cli.policy.diffusion as diffusion

    torch.manual_seed(0)
    net = None
    got = {}
    orig = diffusion.sobolev_output_projection

    def capture(f, d_in, J, n_proj=1, generator=None):
        got["f"] = f
        return orig(f, d_in, J, n_proj, generator)

    jacs = {}
    try:
        diffusion.sobolev_output_projection = capture
        for path in ("total", "cond"):
            opts = dict(method="sdp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, sobolev_path=path)
            policy = make_policy(TrainConfig.of(sobolev_mode="vjp", **opts), 1, 3, 2, 2).double()
            jvp_policy = make_policy(TrainConfig.of(**opts), 1, 3, 2, 2).double()
            if net is None:
                net = policy
            policy.load_state_dict(net.state_dict())      # this path's config, the same weights
            jvp_policy.load_state_dict(net.state_dict())
            sch = make_scheduler(policy.config)
            b = {k: v.double() for k, v in _batch(B=3).items()}
            policy.compute_loss(b, torch.Generator().manual_seed(5))
            J_f = torch.autograd.functional.jacobian(got["f"], torch.zeros(3, 2, dtype=torch.float64))
            J_f = torch.stack([J_f[i, :, :, i] for i in range(3)])           # (B, T_h - 1, A, ndx)
            d = jvp_policy.draw(b, torch.Generator().manual_seed(5))       # the same noise and steps first
            (w, cond_d, tau_d), = d["projections"]
            _, yd = jvp_policy.unet.forward_jvp(d["x"], tau_d, d["k"], d["cond"], cond_d)
            torch.testing.assert_close(yd[:, 1:], torch.einsum("btai,bi->bta", J_f, w))
            jacs[path] = J_f
    finally:
        diffusion.sobolev_output_projection = orig
    g = torch.Generator().manual_seed(5)
    noise = torch.randn(b["tau0"].shape, generator=g).double()
    k = torch.randint(0, 5, (3,), generator=g)
    sab = sch.alphas_cumprod[k].double().sqrt()
    for i in range(3):
        def out(delta):
            tau0 = b["tau0"][i:i + 1] + torch.einsum("btai,i->bta", b["jac"][i:i + 1], delta)
            tau_k = sab[i] * tau0 + (1 - sab[i] ** 2).sqrt() * noise[i:i + 1]
            tau_k = torch.cat([b["a_hist"][i:i + 1], tau_k[:, 1:]], dim=1)
            o = b["obs"][i:i + 1] + torch.einsum("btoi,i->bto", b["obs_jac"][i:i + 1], delta)
            return net(tau_k, k[i:i + 1], b["xi"][i:i + 1], o)[0, 1:]
        brute = torch.autograd.functional.jacobian(out, torch.zeros(2, dtype=torch.float64))
        torch.testing.assert_close(jacs["total"][i], brute)
        assert (jacs["cond"][i] - brute).abs().max() > 1e-6


def test_balance_scale_equalizes_a_zero_predictors_terms_and_ignores_state_units():
    from sdp_cli.losses.sobolev import balance_scale

    g = torch.Generator().manual_seed(0)
    target, J = torch.rand(50, 7, 2, generator=g) - 0.5, torch.randn(50, 7, 2, 3, generator=g) * 20
    rho = balance_scale(target, J)
    dp_zero = (target ** 2).mean()
    sob_zero = (J ** 2).reshape(50, -1).sum(1).mean() / 14
    assert abs(rho * float(sob_zero) - float(dp_zero)) < 1e-6 * float(dp_zero)
    # states in other units (J scaled by c) give the same weighted loss: rho scales by 1 / c^2
    assert balance_scale(target, 10 * J) == pytest.approx(rho / 100, rel=1e-9)
    assert balance_scale(target, torch.zeros_like(J)) == 1.0


def test_inpainting_masks_history_rows():
    """Changing the target of the inpainted row changes neither loss term."""
    cfg = TrainConfig.of(method="sdp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8)
    net = make_policy(cfg, 1, 3, 2, 2)
    b = _batch()
    l1, _ = net.compute_loss(b, torch.Generator().manual_seed(0))
    b2 = dict(b, jac=b["jac"].clone())
    b2["jac"][:, 0] += 5.0
    l2, _ = net.compute_loss(b2, torch.Generator().manual_seed(0))
    torch.testing.assert_close(l1, l2)


def test_scheduler_and_sampling():
    cfg = TrainConfig.of(method="dp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8)
    sch = make_scheduler(cfg)
    assert sch.config.beta_schedule == "squaredcos_cap_v2" and sch.config.prediction_type == "sample"
    assert sch.config.num_train_timesteps == 5 and sch.config.clip_sample
    # add_noise uses the cumulative alpha-bar: tau_k = sqrt(abar) tau_0 + sqrt(1 - abar) eps
    x0, eps, k = torch.ones(1, 8, 1), torch.zeros(1, 8, 1), torch.tensor([2])
    torch.testing.assert_close(sch.add_noise(x0, eps, k), x0 * sch.alphas_cumprod[2].sqrt())
    net = make_policy(cfg, 1, 3, 2, 2).eval()
    a_hist = torch.full((3, 1, 1), 0.3)
    out = net.sample(torch.zeros(3, 2), torch.zeros(3, 1, 3), a_hist, generator=torch.Generator().manual_seed(0))
    assert out.shape == (3, 8, 1)
    torch.testing.assert_close(out[:, :1], a_hist)


def test_fused_tangent_ops_gradcheck():
    from torch import nn

    from sdp_cli.policy.tangent_ops import GroupNormJVP, MishJVP

    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 4, 6, dtype=torch.float64, generator=g, requires_grad=True)
    xd = torch.randn(2, 4, 6, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(MishJVP.apply, (x, xd))
    w = torch.randn(4, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.randn(4, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: GroupNormJVP.apply(*a, 2, 1e-5), (x, xd, w, b))
    # values agree with the library ops and torch.func.jvp
    gn = nn.GroupNorm(2, 4).double()
    with torch.no_grad():
        gn.weight.copy_(w)
        gn.bias.copy_(b)
    y, yd = GroupNormJVP.apply(x, xd, w, b, 2, gn.eps)
    y_ref, yd_ref = jvp(gn, (x,), (xd,))
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(yd, yd_ref)
    y, yd = MishJVP.apply(x, xd)
    y_ref, yd_ref = jvp(nn.functional.mish, (x,), (xd,))
    torch.testing.assert_close(y, y_ref)
    torch.testing.assert_close(yd, yd_ref)


def test_forward_jvp_on_a_sub_batch():
    """Tangents on the first n samples only (``sobolev_fraction``) give the same values and gradients."""
    torch.manual_seed(0)
    net = ConditionalUnet1D(action_dim=2, cond_dim=5, down_dims=(8, 16, 16), n_groups=4, step_embed_dim=8).double()
    B, n = 5, 2
    tau, cond = torch.randn(B, 16, 2, dtype=torch.float64), torch.randn(B, 5, dtype=torch.float64)
    k = torch.tensor([0, 1, 3, 4, 2])
    tau_d, cond_d = torch.randn_like(tau), torch.randn_like(cond)
    y, yd = net.forward_jvp(tau, tau_d, k, cond, cond_d)
    y2, yd2 = net.forward_jvp(tau, tau_d[:n], k, cond, cond_d[:n])
    torch.testing.assert_close(y2, y)
    torch.testing.assert_close(yd2, yd[:n])
    g1 = torch.autograd.grad((yd[:n] ** 2).sum() + y.sum(), list(net.parameters()), allow_unused=True)
    g2 = torch.autograd.grad((yd2 ** 2).sum() + y2.sum(), list(net.parameters()), allow_unused=True)
    for p, a, b in zip(net.parameters(), g1, g2):
        torch.testing.assert_close(torch.zeros_like(p) if a is None else a, torch.zeros_like(p) if b is None else b)
    cfg = TrainConfig.of(method="sdp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, sobolev_fraction=0.5)
    loss, parts = make_policy(cfg, 1, 3, 2, 2).compute_loss(_batch(), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and parts["sobolev"] > 0


@pytest.mark.parametrize("k_rollout", [1, 2, 3, 4, 5])
def test_k_rollout_chain_starts_from_pure_noise(k_rollout):
    """Every chain starts at index K - 1 (pure noise) and steps down its own list to the end.

    diffusers' default "leading" spacing gave set_timesteps(2) -> [2, 0] and set_timesteps(1) -> [0]."""
    from sdp_cli.policy.diffusion import rollout_timesteps

    cfg = TrainConfig.of(method="dp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8)
    policy = make_policy(cfg, 1, 3, 2, 2).eval()
    calls = []
    policy.register_forward_pre_hook(lambda m, args: calls.append(int(args[1][0])))   # the diffusion index
    sch = policy.noise_scheduler
    steps = []
    orig = sch.step
    sch.step = lambda pred, t, tau, **kw: (steps.append((int(t), int(sch.previous_timestep(t)))), orig(pred, t, tau, **kw))[1]
    policy.sample(torch.zeros(2, 2), torch.zeros(2, 1, 3), torch.zeros(2, 1, 1), k_rollout,
                  generator=torch.Generator().manual_seed(0))
    ts = rollout_timesteps(cfg.policy.diffusion_steps, k_rollout)
    assert calls == ts and ts[0] == cfg.policy.diffusion_steps - 1 and len(ts) == k_rollout
    assert [t for t, _ in steps] == ts
    assert [p for _, p in steps] == ts[1:] + [-1]        # each step goes to the next index, the last to clean
    assert k_rollout == 1 or ts[-1] == 0


def test_full_chain_is_unchanged_by_explicit_timesteps():
    """k_rollout = K is bit-identical to the chain diffusers builds from set_timesteps(K)."""
    cfg = TrainConfig.of(method="dp", horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8)
    torch.manual_seed(3)
    net = make_policy(cfg, 1, 3, 2, 2).eval()
    xi, obs, a_hist = torch.randn(3, 2), torch.randn(3, 1, 3), torch.full((3, 1, 1), 0.2)
    new = net.sample(xi, obs, a_hist, cfg.policy.diffusion_steps, generator=torch.Generator().manual_seed(1))
    sch = make_scheduler(cfg)
    sch.set_timesteps(cfg.policy.diffusion_steps)
    g = torch.Generator().manual_seed(1)
    from diffusers.utils.torch_utils import randn_tensor
    with torch.no_grad():
        tau = randn_tensor((3, 8, 1), generator=g, dtype=a_hist.dtype)
        for t in sch.timesteps:
            tau[:, :1] = a_hist
            tau = sch.step(net(tau, torch.full((3,), int(t)), xi, obs), t, tau, generator=g).prev_sample
        tau[:, :1] = a_hist
    assert torch.equal(new, tau)

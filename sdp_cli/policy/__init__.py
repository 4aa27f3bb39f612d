"""Policies: one object per method family (:class:`~sdp_cli.policy.base.Policy`), found through the
method registry (:mod:`sdp_cli.policy.registry`): the DDPM U-Net (SDP, DP) and the MLP (PDDP, PDDP+S).

Rollout-side API (everything in physical units, numpy in / numpy out, batched over instances)::

    from sdp_cli.policy import load_policy
    pol = load_policy("runs/sdp", device="cpu")   # a run folder or a checkpoint file; EMA weights
    pol.task, pol.method, pol.action, pol.chunked, pol.config, pol.normalizer

    # chunked methods (pol.chunked): one reverse DDPM pass, Algorithm 2 lines 3-7
    g = torch.Generator().manual_seed(0)
    tau0 = pol.predict_chunk(xi,        # (B, n_xi)
                             x_hist,    # (B, nx) or (B, T_o, nx): current state x_t
                             u_hist,    # (B, nu) or (B, T_o, nu): previous control u_{t-1}, zeros at t = 0
                             generator=g, k_rollout=None)   # k_rollout <= pol.K denoising steps
    # -> (B, T_h, A): rows [:T_o] are the inpainted history a_hist, play rows [T_o : T_o + T_a]
    #    (T_a <= T_h - T_o). For pol.action == "u" these rows are the torques u_t, u_{t+1}, ...;
    #    otherwise they are g(x_{t+1}), ... (pol.task.state_action) and the controls come from
    #    inverse dynamics.

    # one control per state (not pol.chunked)
    u = pol.act(x, xi)                  # (B, nx), (B, n_xi) -> (B, nu)

Training side (normalized tensors): ``policy.compute_loss(batch, generator) -> (loss, parts)``, driven by
:func:`sdp_cli.training.train_step.step`. The observation fed to the network is ``o_t = (task.observation(x_t),
u_{t-1})``, normalized by the normalizer stored in the checkpoint (:mod:`sdp_cli.data.normalizer`).
"""

from sdp_cli.policy.registry import Method, get_method, make_policy, method_names, register_method

__all__ = ["load_policy", "Policy", "DiffusionUnetPolicy", "MLPPolicy", "TrainConfig", "Method", "get_method",
           "make_policy", "method_names", "register_method"]
_LAZY = {"load_policy": "sdp_cli.policy.api", "Policy": "sdp_cli.policy.base",
         "DiffusionUnetPolicy": "sdp_cli.policy.diffusion", "MLPPolicy": "sdp_cli.policy.mlp",
         "TrainConfig": "sdp_cli.policy.config"}


def __getattr__(name):   # torch is imported when a policy is used, not when the registry is read (CLI start-up)
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sdp_cli.policy' has no attribute {name!r}")

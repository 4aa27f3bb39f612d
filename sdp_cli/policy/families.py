"""The built-in method families (:mod:`sdp_cli.policy.registry`): diffusion (SDP, DP) and MLP
(PDDP, PDDP+S). Heavy modules are imported when a family is used, not when it is registered."""

from __future__ import annotations

from sdp_cli.policy.registry import MethodFamily, register_method


class DiffusionFamily(MethodFamily):
    """Conditional 1-D U-Net + DDPM over chunks ``tau (B, T_h, A)``, conditioned on
    ``o_hist (B, T_o, n_o)`` with ``o = (obs(x), u_prev)`` and on ``xi``; history inpainted."""

    chunked = True

    def dims(self, cfg, task, action):
        from sdp_cli.data.chunks import task_with_action

        return {"n_action": task_with_action(task, action).n_action, "n_obs": task.n_obs + task.nu,
                "n_xi": task.n_xi, "ndx": task.ndx}

    def dataset(self, cfg, task, arrays, with_jacobians):
        from sdp_cli.data.chunks import ChunkDataset

        action = cfg.action or task.action
        return ChunkDataset(task, arrays, cfg.T_h, cfg.T_o, action, with_jacobians=with_jacobians), action

    def build_net(self, cfg, dims):
        from sdp_cli.policy.diffusion import DiffusionNet

        return DiffusionNet(cfg, dims["n_action"], dims["n_obs"], dims["n_xi"], dims["ndx"])

    def scheduler(self, cfg):
        from sdp_cli.policy.diffusion import make_scheduler

        return make_scheduler(cfg)

    def loss(self, cfg, scheduler, sobolev, sobolev_scale):
        from sdp_cli.policy.diffusion import diffusion_loss

        return lambda net, b, g: diffusion_loss(net, scheduler, b, cfg, g, sobolev=sobolev,
                                                sobolev_scale=sobolev_scale)

    def balance_terms(self, cfg, tensors):
        return tensors["tau0"][:, cfg.T_o:], tensors["jac"][:, cfg.T_o:]


class MLPFamily(MethodFamily):
    """``u (B, nu) = MLP(obs(x) (B, n_obs), xi (B, n_xi))`` on (state, control) pairs."""

    chunked = False

    def dims(self, cfg, task, action):
        return {"n_action": task.nu, "n_obs": task.n_obs, "n_xi": task.n_xi, "ndx": task.ndx}

    def dataset(self, cfg, task, arrays, with_jacobians):
        from sdp_cli.data.chunks import PairDataset

        return PairDataset(task, arrays, with_jacobians=with_jacobians), "u"

    def build_net(self, cfg, dims):
        from sdp_cli.policy.mlp import MLPNet

        return MLPNet(cfg, dims["n_action"], dims["n_obs"], dims["n_xi"], dims["ndx"])

    def loss(self, cfg, scheduler, sobolev, sobolev_scale):
        from sdp_cli.policy.mlp import mlp_loss

        return lambda net, b, g: mlp_loss(net, b, cfg, g, sobolev=sobolev, sobolev_scale=sobolev_scale)

    def balance_terms(self, cfg, tensors):
        return tensors["u"], tensors["jac"]


def register_builtin() -> None:
    """Register sdp, dp, pddp and pddp_s (run when this module is imported)."""
    diffusion, mlp = DiffusionFamily(), MLPFamily()
    register_method("sdp", diffusion, sobolev=True, description="Sobolev diffusion policy, eq. (6)")
    register_method("dp", diffusion, sobolev=False, description="diffusion policy, eq. (2)")
    register_method("pddp", mlp, sobolev=False, description="MLP regression on the TO data")
    register_method("pddp_s", mlp, sobolev=True, description="MLP with the Sobolev term of eq. (4)")


register_builtin()

"""Trained policies as used at rollout time (see :mod:`sdp_cli.policy` for the contract)."""

from __future__ import annotations

import numpy as np
import torch

from sdp_cli.data.artifacts import resolve_recorded
from sdp_cli.data.chunks import task_with_action
from sdp_cli.policy.checkpoint import load_checkpoint, net_from_checkpoint, resolve_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.tasks import Task, get_task
from sdp_cli.tasks.base import check_task_params


def _t(a, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=np.float64) if not torch.is_tensor(a) else a,
                           device=device).to(torch.float32)


class Policy:
    """Common part: the task, the config and the normalizer-carrying network."""

    def __init__(self, ck: dict, device="cpu", use_ema: bool = True):
        self.device = torch.device(device)
        self.config = TrainConfig.from_dict(ck["config"])
        self.method = self.config.method
        self.action = ck["action"]
        self.task_options: dict = dict(ck.get("task_options") or {})   # recorded by rollouts, checked by refine
        self.task: Task = get_task(ck["task"], **self.task_options)
        check_task_params(self.task, ck.get("task_params"), "policy checkpoint")
        if self.config.is_diffusion:   # the policy's action variable may differ from the task's default
            self.task = task_with_action(self.task, self.action)
        self.task_name = ck["task"]
        self.checkpoint_epoch = ck.get("epoch")
        self.dataset_info = dict(ck.get("dataset") or {})   # path, sha256, n_traj, T of the training data
        self.net = net_from_checkpoint(ck, use_ema).to(self.device).eval()
        self.norm = self.net.normalizer
        self.is_diffusion = self.config.is_diffusion

    def _obs(self, x: np.ndarray, u_prev: np.ndarray) -> torch.Tensor:
        """Normalized ``o = (obs(x), u_prev)``: (B, nx), (B, nu) -> (B, n_o)."""
        o = np.concatenate([self.task.observation(np.asarray(x, float)), np.asarray(u_prev, float)], -1)
        return self.norm.normalize("obs", _t(o, self.device))


class DiffusionPolicy(Policy):
    """``predict_chunk``: one reverse DDPM pass (Algorithm 2, lines 3-7)."""

    @property
    def T_h(self) -> int:
        return self.config.T_h

    @property
    def T_o(self) -> int:
        return self.config.T_o

    @property
    def K(self) -> int:
        return self.config.K

    def a_hist(self, x_hist: np.ndarray, u_hist: np.ndarray) -> np.ndarray:
        """History actions: ``u_{t-1}`` for torque control, ``g(x_t)`` otherwise: (B, T_o, A)."""
        if self.action == "u":
            return np.asarray(u_hist, float)
        return self.task.state_action(np.asarray(x_hist, float))

    def predict_chunk(self, xi, x_hist, u_hist, generator: torch.Generator | None = None,
                      k_rollout: int | None = None) -> np.ndarray:
        """``tau_0 (B, T_h, A)``, unnormalized, rows ``[:T_o]`` = the inpainted history.

        ``xi (B, n_xi)``; ``x_hist (B, T_o, nx)`` or ``(B, nx)`` current state(s);
        ``u_hist (B, T_o, nu)`` or ``(B, nu)`` previous control(s) ``u_{t-1}`` (zeros at t = 0).
        Play rows ``[T_o : T_o + T_a]``. ``k_rollout`` (<= K) denoising steps, default K.
        """
        from sdp_cli.policy.diffusion import make_scheduler, sample_chunk

        x_hist = np.asarray(x_hist, float)
        u_hist = np.asarray(u_hist, float)
        if x_hist.ndim == 2:
            x_hist = x_hist[:, None]
        if u_hist.ndim == 2:
            u_hist = u_hist[:, None]
        if k_rollout is not None and not 1 <= k_rollout <= self.K:
            from sdp_cli.errors import SdpError
            raise SdpError(f"k_rollout must be in [1, {self.K}], got {k_rollout}")
        obs = self._obs(x_hist, u_hist)                                       # (B, T_o, n_o)
        a_hist = self.norm.normalize("action", _t(self.a_hist(x_hist, u_hist), self.device))
        xi_n = self.norm.normalize("xi", _t(xi, self.device))
        if not hasattr(self, "_scheduler"):
            self._scheduler = make_scheduler(self.config)
        tau = sample_chunk(self.net, self._scheduler, xi_n, obs, a_hist, self.T_h, k_rollout, generator)
        return self.norm.unnormalize("action", tau).double().cpu().numpy()


class MLPPolicy(Policy):
    """``act``: one control per state (PDDP, PDDP+S)."""

    @torch.no_grad()
    def act(self, x, xi) -> np.ndarray:
        """``u (B, nu)`` from ``x (B, nx)`` and ``xi (B, n_xi)`` (unnormalized, not clipped)."""
        x = np.asarray(x, float)
        o = _t(self.task.observation(x), self.device)
        n = o.shape[-1]
        o = (o - self.norm.obs_center[:n]) / self.norm.obs_scale[:n]
        u = self.net(o, self.norm.normalize("xi", _t(xi, self.device)))
        return self.norm.unnormalize("action", u).double().cpu().numpy()


def load_policy(path, device="cpu", use_ema: bool = True) -> DiffusionPolicy | MLPPolicy:
    """Load a trained policy from a checkpoint file or a run folder (``checkpoint.pt``)."""
    path = resolve_checkpoint(path)
    ck = load_checkpoint(path, map_location=device)
    chunked = TrainConfig.from_dict(ck["config"]).family.chunked   # the method's family, from the registry
    policy = (DiffusionPolicy if chunked else MLPPolicy)(ck, device, use_ema)
    if policy.dataset_info.get("path"):   # recorded relative to the checkpoint's folder
        policy.dataset_info["path"] = str(resolve_recorded(policy.dataset_info["path"], path.parent))
    return policy

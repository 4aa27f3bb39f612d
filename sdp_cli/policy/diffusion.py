"""SDP and DP: the DDPM diffusion policy over action chunks (config, normalizer, U-Net, scheduler),
with its training loss (eqs. (2), (6)) and sampling (Algorithm 2). Registered as ``sdp`` and ``dp``.

Everything inside works in normalized units (:mod:`sdp_cli.data.normalizer`). The
scheduler is diffusers' ``DDPMScheduler`` with the squared-cosine schedule
(``squaredcos_cap_v2``), ``prediction_type="sample"`` (the network predicts ``tau_0``) and
``K`` train steps; ``clip_sample`` clips predictions to [-1, 1], matching the min-max
normalization of actions. diffusers' timestep index ``k - 1`` is the paper's ``k``.

Inpainting: the first ``T_o`` rows of ``tau_k`` are replaced by ``a_hist`` before every
network call, in training (Algorithm 1 line 19) and sampling (Algorithm 2 line 5); these
rows are masked out of the loss.

Sobolev term: the derivative is taken w.r.t. one leaf ``delta (B, ndx)``, a normalized
tangent perturbation of ``x_hist``, which feeds the observation ``o_hist`` (through
``obs_jac``) and, for state control, the inpainted ``a_hist`` (through ``a_hist_jac``).
Both enter linearly, which is exact to first order at ``delta = 0`` and is all the
Sobolev term needs (values at ``delta = 0`` are the data).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from diffusers.utils.torch_utils import randn_tensor
from diffusers import DDPMScheduler

from sdp_cli.data.normalizer import Normalizer
from sdp_cli.errors import SdpError
from sdp_cli.losses.sobolev import random_unit, sobolev_output_projection
from sdp_cli.policy.base import Policy, as_tensor
if TYPE_CHECKING:   # annotations only: the config does not import the families at run time either
    from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.unet import ConditionalUnet1D, compile_unet, member_view, stack_members


def make_scheduler(cfg: TrainConfig) -> DDPMScheduler:
    return DDPMScheduler(num_train_timesteps=cfg.policy.diffusion_steps, beta_schedule="squaredcos_cap_v2",
                         clip_sample=cfg.policy.clip_sample, prediction_type="sample")


def rollout_timesteps(K: int, k_rollout: int) -> list[int]:
    """The ``k_rollout`` scheduler indices of a reverse chain over a model trained with ``K`` steps.

    Always starts from pure noise (index ``K - 1``) and ends at 0 (``k_rollout >= 2``), evenly
    spaced: K = 5 gives [4, 3, 2, 1, 0], [4, 2, 0], [4, 0] and [4]. Passed to diffusers
    explicitly, so every diffusers version gives the same chain; its default "leading" spacing
    would start ``set_timesteps(2)`` at index 2 and ``set_timesteps(1)`` at 0, feeding pure noise
    as an almost clean sample.
    """
    if not 1 <= k_rollout <= K:
        raise ValueError(f"k_rollout must be in [1, {K}], got {k_rollout}")
    if k_rollout == 1:
        return [K - 1]
    return [int(t) for t in np.round(np.linspace(K - 1, 0, k_rollout))]


def chunk_tangents(w, obs_jac, a_hist, a_hist_jac, rest, rest_jac):
    """``(o_d (n, T_o, n_o), tau_d (n, T_h, A) or None)``: the tangents of the observation history and of the
    network's input chunk (history rows, then the noisy rows) along state directions ``w (n, ndx)`` of the first
    ``n`` samples; ``a_hist_jac`` / ``rest_jac`` None: those rows do not depend on the state."""
    n = w.shape[0]
    o_d = torch.einsum("btoi,bi->bto", obs_jac[:n], w)
    if a_hist_jac is None and rest_jac is None:
        return o_d, None
    a_d = torch.zeros_like(a_hist[:n]) if a_hist_jac is None else torch.einsum("btai,bi->bta", a_hist_jac[:n], w)
    r_d = torch.zeros_like(rest[:n]) if rest_jac is None else torch.einsum("btai,bi->bta", rest_jac[:n], w)
    return o_d, torch.cat([a_d, r_d], dim=1)


class DiffusionUnetPolicy(Policy):
    """Conditional 1-D U-Net + DDPM over chunks ``tau (B, T_h, A)``, conditioned on ``o_hist (B, T_o, n_o)``
    with ``o = (obs(x), u_prev)`` and on ``xi``; history inpainted.

    ``forward(tau_k, k, xi_n, obs_n) -> tau_0`` prediction, shapes ``tau_k (B, T_h, A)``, ``k (B,)``
    scheduler indices, ``xi_n (B, n_xi)``, ``obs_n (B, T_o, n_o)``; all normalized. State dict:
    ``normalizer.*``, ``unet.*``.
    """

    chunked = True
    stackable = True    # sdp_cli.training.train_stack trains several runs of this family as one stacked U-Net
    compilable = True   # TrainConfig.compile: the U-Net's forward and tangent pass (compile_network)

    def __init__(self, config: TrainConfig, dims: dict):
        super().__init__(config, dims)
        d = self.dims
        self.normalizer = Normalizer(d["n_action"], d["n_obs"], d["n_xi"], d["ndx"])
        p = config.policy
        self.unet = ConditionalUnet1D(d["n_action"], d["n_xi"] + p.n_obs_steps * d["n_obs"], p.down_dims,
                                      p.kernel_size, p.n_groups, p.step_embed_dim)
        self.noise_scheduler = make_scheduler(config)

    def compile_network(self) -> None:
        """The U-Net's ``forward`` and ``forward_jvp`` through ``torch.compile`` (:mod:`sdp_cli.policy.compiling`);
        the rest of a step (draws, optimizer, EMA) stays eager."""
        compile_unet(self.unet)

    # ------------------------------------------------------------------ configuration
    @classmethod
    def check_config(cls, config) -> None:
        """The U-Net's rules: T_h divisible by 2^(levels - 1) (the down path halves it per level), channels
        divisible by the GroupNorm groups."""
        p = config.policy
        levels = len(p.down_dims)
        if p.horizon % (2 ** (levels - 1)):
            raise SdpError(f"horizon T_h = {p.horizon} must be divisible by 2^(len(down_dims) - 1) = "
                           f"{2 ** (levels - 1)} for the U-Net")
        bad = [d for d in p.down_dims if d % p.n_groups]
        if bad:
            raise SdpError(f"down_dims {bad} not divisible by n_groups = {p.n_groups}")

    @classmethod
    def sampler_steps(cls, config) -> int:
        """The reverse chain has at most K = ``diffusion_steps`` network calls (``k_rollout`` <= K)."""
        return config.policy.diffusion_steps

    # ------------------------------------------------------------------ data
    @classmethod
    def make_dataset(cls, config, task, arrays, with_jacobians):
        from sdp_cli.data.chunks import ChunkDataset

        p = config.policy
        action = cls.action_for(config, task)
        return ChunkDataset(task, arrays, p.horizon, p.n_obs_steps, action, with_jacobians=with_jacobians), action

    @classmethod
    def dims_for(cls, config, task, action):
        from sdp_cli.data.chunks import task_with_action

        return {"n_action": task_with_action(task, action).n_action, "n_obs": task.n_obs + task.nu,
                "n_xi": task.n_xi, "ndx": task.ndx}

    def balance_terms(self, tensors):
        return tensors["tau0"][:, self.T_o:], tensors["jac"][:, self.T_o:]

    # ------------------------------------------------------------------ network
    def forward(self, tau_k, k, xi_n, obs_n):
        return self.unet(tau_k, k, torch.cat([xi_n, obs_n.flatten(1)], dim=-1))

    def forward_jvp(self, tau_k, tau_d, k, xi_n, obs_n, obs_d):
        """``(y, dy)`` along tangents ``tau_d`` (or None) of ``tau_k`` and ``obs_d`` of ``obs_n``."""
        cond_d = torch.cat([torch.zeros_like(xi_n[: obs_d.shape[0]]), obs_d.flatten(1)], dim=-1)
        return self.unet.forward_jvp(tau_k, tau_d, k, torch.cat([xi_n, obs_n.flatten(1)], dim=-1), cond_d)

    # ------------------------------------------------------------------ training
    def compute_loss(self, batch: dict, generator: torch.Generator | None = None):
        """``(loss, {"dp": ..., "sobolev": ...})`` for a batch of normalized chunk tensors.

        ``batch``: ``tau0 (B, T_h, A)``, ``a_hist (B, T_o, A)``, ``obs (B, T_o, n_o)``,
        ``obs_jac (B, T_o, n_o, ndx)``, ``xi (B, n_xi)``; for Sobolev (``sdp``) also ``jac (B, T_h, A, ndx)``
        and, for state control, ``a_hist_jac (B, T_o, A, ndx)``. The Sobolev term is multiplied by
        :attr:`sobolev_scale` (:func:`~sdp_cli.losses.sobolev.balance_scale`), then by ``sobolev_alpha``.
        ``sobolev_path == "total"`` also differentiates through the noisy rows of ``tau_k`` (tangent
        ``sqrt(alpha_bar_k) J`` on rows ``T_o:``); "cond" holds them fixed.

        Without the Sobolev term or in its jvp mode this is :meth:`draw`, the U-Net on the draw's inputs and
        :meth:`loss_from`: the same three a stack of runs (:class:`StackedDiffusion`) applies member by member.
        """
        if self.config.uses_sobolev and self.config.sobolev.mode == "vjp":
            return self._vjp_loss(batch, generator)
        d = self.draw(batch, generator)
        if not d["projections"]:
            return self.loss_from(d, self.unet(d["x"], d["k"], d["cond"]), [])
        y, ydots = None, []
        for _, cond_d, tau_d in d["projections"]:
            y, yd = self.unet.forward_jvp(d["x"], tau_d, d["k"], d["cond"], cond_d)
            ydots.append(yd)
        return self.loss_from(d, y, ydots)

    def _noised(self, batch: dict, generator):
        """The diffusion draws of a step: noise, then steps ``k (B,)``; ``(k, tau_k (B, T_h, A))``."""
        tau0 = batch["tau0"]
        dev = tau0.device
        gdev = generator.device if generator is not None else dev   # CPU generator: same draws on a GPU
        noise = torch.randn(tau0.shape, generator=generator, device=gdev).to(dev)
        k = torch.randint(0, self.K, (tau0.shape[0],), generator=generator, device=gdev).to(dev)
        return k, self.noise_scheduler.add_noise(tau0, noise, k)

    def _rest_jac(self, batch: dict, k):
        """``sobolev_path == "total"``: the noisy rows depend on x_t too, d tau_k / dx = sqrt(alpha_bar_k)
        d tau_0 / dx (rows ``T_o:``); "cond": None."""
        if self.config.sobolev.path != "total":
            return None
        tau0 = batch["tau0"]
        sab = self.noise_scheduler.alphas_cumprod.to(tau0.device)[k].sqrt().to(tau0.dtype)
        return sab[:, None, None, None] * batch["jac"][:, self.T_o:]

    def draw(self, batch: dict, generator: torch.Generator | None = None) -> dict:
        """A step's random draws and the U-Net's inputs (no Sobolev term, or its jvp mode): noise, diffusion
        steps, then the Sobolev directions ``w (n_s, ndx)``, in this order from ``generator``.

        Returns ``B``, ``x (B, T_h, A)`` (history inpainted), ``k (B,)``, ``cond (B, n_cond)``,
        ``target (B, T_h - T_o, A)`` and ``projections``: per direction ``(w, cond_d (n_s, n_cond),
        tau_d (n_s, T_h, A) or None)``, the tangents of the condition and of the input chunk; with the Sobolev
        term also ``n_s`` (the first samples it uses, ``sobolev_fraction``), ``J (n_s, d_out, ndx)`` and
        ``w_cap`` (``sobolev_cap``'s weights or None)."""
        s, T_o = self.config.sobolev, self.T_o
        tau0, a_hist, obs, xi = batch["tau0"], batch["a_hist"], batch["obs"], batch["xi"]
        B = tau0.shape[0]
        k, tau_k = self._noised(batch, generator)
        rest = tau_k[:, T_o:]
        d = {"B": B, "x": torch.cat([a_hist, rest], dim=1), "k": k, "cond": torch.cat([xi, obs.flatten(1)], -1),
             "target": tau0[:, T_o:], "projections": []}
        if not self.config.uses_sobolev:
            return d
        n_s = max(1, round(s.fraction * B))
        J = batch["jac"][:n_s, T_o:]
        d.update(n_s=n_s, J=J.reshape(n_s, -1, J.shape[-1]), w_cap=batch.get("sob_weight"))
        rest_jac = self._rest_jac(batch, k)
        for _ in range(s.n_proj):
            w = random_unit((n_s, J.shape[-1]), generator, tau0.device, J.dtype)
            o_d, tau_d = chunk_tangents(w, batch["obs_jac"], a_hist, batch.get("a_hist_jac"), rest, rest_jac)
            d["projections"].append((w, torch.cat([torch.zeros_like(xi[:n_s]), o_d.flatten(1)], dim=-1), tau_d))
        return d

    def loss_from(self, d: dict, y: torch.Tensor, ydots: list):
        """``(loss, parts)`` of a :meth:`draw` ``d`` from the U-Net's output ``y (B, T_h, A)`` and, per
        projection, its tangent ``ydot (n_s, T_h, A)``: the regression term (eq. (2)) plus ``alpha`` times the
        balanced Sobolev term (input projection: ``(d_in / d_out) ||J w - ydot||^2``, averaged over the
        projections)."""
        T_o = self.T_o
        dp = ((y[:, T_o:] - d["target"]) ** 2).mean()
        if not self.config.uses_sobolev:
            return dp, {"dp": dp.detach(), "sobolev": torch.zeros((), device=dp.device)}
        n, J = d["n_s"], d["J"]
        term = 0.0
        for (w, _, _), yd in zip(d["projections"], ydots):
            target = torch.einsum("boi,bi->bo", J, w)
            term = term + ((target - yd[:, T_o:].reshape(n, -1)) ** 2).sum(-1)
        term = term * (J.shape[-1] / J.shape[1]) / len(ydots)
        wc = d["w_cap"]
        return self._total(dp, term, None if wc is None else wc[:n])

    def _vjp_loss(self, batch: dict, generator):
        """The Sobolev term by output projection (eq. (6), reverse over reverse; ``sobolev_mode vjp``)."""
        cfg, T_o = self.config.sobolev, self.T_o
        tau0, a_hist, obs, xi = batch["tau0"], batch["a_hist"], batch["obs"], batch["xi"]
        k, tau_k = self._noised(batch, generator)
        rest = tau_k[:, T_o:]
        obs_jac, a_hist_jac = batch["obs_jac"], batch.get("a_hist_jac")
        rest_jac = self._rest_jac(batch, k)

        def f(delta):   # delta (B, ndx) -> predicted tau_0 rows T_o: (B, T_h - T_o, A)
            o = obs + torch.einsum("btoi,bi->bto", obs_jac, delta)
            a = a_hist if a_hist_jac is None else a_hist + torch.einsum("btai,bi->bta", a_hist_jac, delta)
            r = rest if rest_jac is None else rest + torch.einsum("btai,bi->bta", rest_jac, delta)
            return self(torch.cat([a, r], dim=1), k, xi, o)[:, T_o:]

        J = batch["jac"][:, T_o:]
        pred, term = sobolev_output_projection(f, J.shape[-1], J, cfg.n_proj, generator)
        dp = ((pred - tau0[:, T_o:]) ** 2).mean()
        return self._total(dp, term, batch.get("sob_weight"))

    def _total(self, dp, term, w_cap):
        """``(loss, parts)``: the regression term plus ``alpha`` times the balanced Sobolev term, its per-sample
        errors ``term (n,)`` weighted by ``w_cap (n,)`` (``sobolev_cap``) where given."""
        sob = self.sobolev_scale * (term.mean() if w_cap is None else (w_cap * term).mean())
        return dp + self.config.sobolev.weight * sob, {"dp": dp.detach(), "sobolev": sob.detach()}

    @classmethod
    def stack(cls, policies: list["DiffusionUnetPolicy"]) -> "StackedDiffusion":
        """R policies of one architecture trained as one network (:class:`StackedDiffusion`)."""
        return StackedDiffusion(policies)

    # ------------------------------------------------------------------ sampling
    @torch.no_grad()
    def sample(self, xi_n, obs_n, a_hist_n, k_rollout: int | None = None,
               generator: torch.Generator | list | None = None):
        """Reverse DDPM (Algorithm 2 lines 3-7), normalized: ``xi_n (B, n_xi)``, ``obs_n (B, T_o, n_o)``,
        ``a_hist_n (B, T_o, A)`` -> ``(B, T_h, A)`` with the history inpainted. A list of generators (one
        per instance) makes batched and one-by-one sampling identical."""
        scheduler = self.noise_scheduler
        B, T_o, A = a_hist_n.shape
        scheduler.set_timesteps(timesteps=rollout_timesteps(self.K, k_rollout or self.K), device=a_hist_n.device)
        tau = randn_tensor((B, self.T_h, A), generator=generator, device=a_hist_n.device, dtype=a_hist_n.dtype)
        for t in scheduler.timesteps:
            tau[:, :T_o] = a_hist_n
            kk = torch.full((B,), int(t), device=tau.device, dtype=torch.long)
            pred = self(tau, kk, xi_n, obs_n)
            tau = scheduler.step(pred, t, tau, generator=generator).prev_sample
        tau[:, :T_o] = a_hist_n
        return tau

    # ------------------------------------------------------------------ rollout (physical units)
    @property
    def T_h(self) -> int:
        """The chunk length (``policy.horizon``)."""
        return self.config.policy.horizon

    @property
    def T_o(self) -> int:
        """Observed steps (``policy.n_obs_steps``)."""
        return self.config.policy.n_obs_steps

    @property
    def K(self) -> int:
        """Diffusion steps of training (``policy.diffusion_steps``)."""
        return self.config.policy.diffusion_steps

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
        x_hist = np.asarray(x_hist, float)
        u_hist = np.asarray(u_hist, float)
        if x_hist.ndim == 2:
            x_hist = x_hist[:, None]
        if u_hist.ndim == 2:
            u_hist = u_hist[:, None]
        if k_rollout is not None and not 1 <= k_rollout <= self.K:
            raise SdpError(f"k_rollout must be in [1, {self.K}], got {k_rollout}")
        obs = self._obs(x_hist, u_hist)                                       # (B, T_o, n_o)
        a_hist = self.normalizer.normalize("action", as_tensor(self.a_hist(x_hist, u_hist), self.device))
        xi_n = self.normalizer.normalize("xi", as_tensor(xi, self.device))
        tau = self.sample(xi_n, obs, a_hist, k_rollout, generator)
        return self.normalizer.unnormalize("action", tau).double().cpu().numpy()


class StackedDiffusion:
    """R diffusion policies of one architecture as one stacked U-Net (:mod:`sdp_cli.policy.unet`,
    ``members=R``): each policy's U-Net weights become views into the stack's, so its optimiser, EMA and
    checkpoint stay its own (:mod:`sdp_cli.training.train_stack`). :meth:`losses` is every member's
    :meth:`~DiffusionUnetPolicy.loss_from` of its own :meth:`~DiffusionUnetPolicy.draw` through one call of the
    stacked network (one per Sobolev projection), members with fewer samples padded with zero rows that stay out
    of their losses."""

    def __init__(self, policies: list[DiffusionUnetPolicy]):
        self.policies, self.R = policies, len(policies)
        self.net = stack_members([p.unet for p in policies])
        if policies[0].config.compile:
            compile_unet(self.net)
        stacked = dict(self.net.named_parameters())
        #: the stacked parameters in every member's ``parameters()`` order (its optimiser's)
        self.parameters = []
        for i, pol in enumerate(policies):
            for name, sp in pol.unet.named_parameters():
                sp.data = member_view(stacked[name].data, sp.dim(), self.R, i)   # the solo weights live here
                if i == 0:
                    self.parameters.append(stacked[name])

    def zero_grad(self) -> None:
        self.net.zero_grad(set_to_none=True)

    @staticmethod
    def _pad(parts: list, n: int) -> torch.Tensor:
        """Stack member tensors ``(n_r, ...)`` into ``(n, R, ...)``, zero rows below each member's own."""
        ref = next(p for p in parts if p is not None)
        out = ref.new_zeros((n, len(parts), *ref.shape[1:]))
        for i, p in enumerate(parts):
            if p is not None:
                out[: p.shape[0], i] = p
        return out

    def losses(self, draws: list) -> list:
        """``[(loss, parts) or None]`` per member from its draw (None: the member takes no step)."""
        act = [d for d in draws if d is not None]
        Bm = max(d["B"] for d in act)
        x, k, cond = (self._pad([d and d[key] for d in draws], Bm) for key in ("x", "k", "cond"))
        ydots = [[] for _ in draws]
        n_proj = max(len(d["projections"]) for d in act)
        if not n_proj:
            y = self.net(x, k, cond)
        else:   # members with fewer projections (DP: none) get zero tangents whose outputs they do not read
            n_max = max(d["n_s"] for d in act if d["projections"])
            for j in range(n_proj):
                pr = [d["projections"][j] if d is not None and j < len(d["projections"]) else None for d in draws]
                cond_d = self._pad([p and p[1] for p in pr], n_max)
                tau_d = (self._pad([p and p[2] for p in pr], n_max) if any(p and p[2] is not None for p in pr)
                         else None)
                y, yd = self.net.forward_jvp(x, tau_d, k, cond, cond_d)
                for i, (d, p) in enumerate(zip(draws, pr)):
                    if p is not None:
                        ydots[i].append(yd[: d["n_s"], i])
        return [None if d is None else pol.loss_from(d, y[: d["B"], i], ydots[i])
                for i, (d, pol) in enumerate(zip(draws, self.policies))]

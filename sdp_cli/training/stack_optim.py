"""Every member's gradient clipping, AdamW step and EMA update of a stack (:class:`sdp_cli.training.train_step.Stack`) in a
few whole-stack operations.

A solo run's optimisation touches its ~200 parameter tensors one by one (``clip_grad_norm_``, AdamW with
``foreach``, diffusers' ``EMAModel``): on a CPU that is ~9 ms of per-tensor overhead a step for ~0.3 M weights,
which R members in a stack would pay R times (``bench/profile_step.py``). Here the members' gradients, AdamW
moments and EMA weights are ``(R, N)`` matrices (row ``r``: member ``r``'s N weights, in its
``policy.parameters()`` order): the norms and clipping are one operation each, the EMA one ``lerp`` with each
member's decay as an ``(R, 1)`` column, and AdamW one call of torch's fused kernel per member on its row.

Each member keeps its own: gradient-norm bound, learning rate (read from its optimizer, which its own LR schedule
sets), betas, epsilon, weight decay, AdamW step count, EMA warm-up and decay. Its optimizer state (``exp_avg``,
``exp_avg_sq``, ``step``) and EMA weights stay those of its solo ``torch.optim.AdamW`` and ``EMAModel``: the
tensors are views into the matrices, so a member's checkpoint is a solo one and a solo run resumes it. The
arithmetic is torch's AdamW (decoupled weight decay, bias-corrected moments) and diffusers' EMA update; an inactive
(finished) member's weights, moments and EMA are left exactly as they are.
"""

from __future__ import annotations

import torch

try:   # the dtype torch's AdamW gives a fresh "step" (float64 under a float64 default dtype)
    from torch.optim.optimizer import _get_scalar_dtype
except ImportError:   # pragma: no cover - older torch
    def _get_scalar_dtype():
        return torch.float32


class StackedOptimisation:
    """Clipping, AdamW and EMA of the members (``runs``, :class:`sdp_cli.training.train.Run`) of one stacked network whose
    parameters are ``stacked`` (each ``(R, ...)`` or ``(R * c, ...)``, member ``r``'s block the ``r``-th of R),
    in the order of every member's ``policy.parameters()``."""

    def __init__(self, runs: list, stacked: list[torch.Tensor]):
        self.runs, self.R = runs, len(runs)
        self.stacked = stacked
        self.sizes = [p.numel() // self.R for p in stacked]
        ref = stacked[0]
        shape = (self.R, sum(self.sizes))
        self.m, self.v, self.shadow = (ref.new_zeros(shape) for _ in range(3))
        self.steps = []   # per member: one "step" tensor shared by its parameters' AdamW states
        for i, run in enumerate(runs):
            params = list(run.policy.parameters())
            groups = run.opt.param_groups
            if len(groups) != 1 or groups[0]["amsgrad"] or groups[0]["maximize"] or len(params) != len(stacked):
                raise ValueError("a stacked member needs one plain AdamW parameter group over its U-Net")
            step = None
            off = 0
            for j, (p, n) in enumerate(zip(params, self.sizes)):
                st = run.opt.state[p]
                rows = [self.m[i, off:off + n], self.v[i, off:off + n], self.shadow[i, off:off + n]]
                if st:
                    rows[0].copy_(st["exp_avg"].flatten())
                    rows[1].copy_(st["exp_avg_sq"].flatten())
                    step = step if step is not None else st["step"].clone()
                rows[2].copy_(run.ema.shadow_params[j].flatten())
                st["exp_avg"], st["exp_avg_sq"] = rows[0].view_as(p), rows[1].view_as(p)
                run.ema.shadow_params[j] = rows[2].view_as(p)
                off += n
            step = step if step is not None else torch.tensor(0.0, dtype=_get_scalar_dtype())
            for p in params:
                run.opt.state[p]["step"] = step
            self.steps.append(step)
        self.bound = self._column([r.cfg.optim.grad_clip for r in runs]).squeeze(1)

    def _column(self, values) -> torch.Tensor:
        return torch.tensor(values, dtype=self.m.dtype, device=self.m.device).unsqueeze(1)

    @torch.no_grad()
    def step(self, active: list[bool]) -> torch.Tensor:
        """One step of the ``active`` members after a backward through the stack (their LR schedules not yet
        stepped, as in a solo step); returns every member's gradient norm before clipping, ``(R,)``."""
        R = self.R
        G = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(R, -1)
                       for p in self.stacked], dim=1)
        norms = torch.linalg.vector_norm(G, dim=1)
        G.mul_((self.bound / (norms + 1e-6)).clamp(max=1.0).unsqueeze(1))   # clip_grad_norm_'s coefficient
        P = torch.cat([p.detach().reshape(R, -1) for p in self.stacked], dim=1)
        ema = []
        for i, (run, on, step) in enumerate(zip(self.runs, active, self.steps)):
            if not on:
                ema.append(0.0)
                continue
            g = run.opt.param_groups[0]
            step += 1
            # torch's fused AdamW kernel (one pass over the member's row; the solo run's foreach AdamW computes
            # the same terms in several passes): decoupled weight decay, moments, bias-corrected step
            torch._fused_adamw_([P[i]], [G[i]], [self.m[i]], [self.v[i]], [], [step.to(P.device)], lr=g["lr"],
                                beta1=g["betas"][0], beta2=g["betas"][1], weight_decay=g["weight_decay"],
                                eps=g["eps"], amsgrad=False, maximize=False)
            run.opt._opt_called = True   # for its LR schedule's "stepped before the optimizer" check: it has
            run.ema.optimization_step += 1
            run.ema.cur_decay_value = run.ema.get_decay(run.ema.optimization_step)
            ema.append(1 - run.ema.cur_decay_value)
        torch._foreach_copy_([p.detach().view(R, -1) for p in self.stacked], list(P.split(self.sizes, dim=1)))
        self.shadow.lerp_(P, self._column(ema))   # diffusers' EMA: shadow -= (1 - decay) (shadow - weights)
        return norms

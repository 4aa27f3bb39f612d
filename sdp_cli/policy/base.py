"""The policy object every method family implements (after lerobot's ``PreTrainedPolicy``).

A policy is one ``nn.Module`` that owns its configuration (:class:`~sdp_cli.policy.config.TrainConfig`),
its normalizer (:class:`~sdp_cli.data.normalizer.Normalizer`, a submodule: its ranges travel in the
state dict), its network (a bare ``nn.Module`` such as the U-Net) and, for diffusion, its noise
scheduler. Everything the project does with a policy goes through this interface:

- **data** (class methods, before a policy exists): :meth:`Policy.make_dataset` cuts a TO dataset into
  the family's samples and names the action variable; :meth:`Policy.dims_for` gives the network sizes;
- **training** (normalized tensors): :meth:`Policy.compute_loss` ``(batch, generator) -> (loss, parts)``
  with ``parts = {"dp": regression, "sobolev": term}``; :meth:`Policy.balance_terms` feeds the Sobolev
  balance; :func:`sdp_cli.training.train_step.step` is the one optimisation step (solo and stacked trainers, estimate);
  a family that sets :attr:`Policy.stackable` also gives ``stack(policies)`` and ``draw``/``loss_from``
  (:class:`~sdp_cli.policy.diffusion.StackedDiffusion`);
- **rollout** (physical units, numpy, batched): after :meth:`Policy.bind` (done by
  :func:`~sdp_cli.policy.api.load_policy`), every family answers the one action API of Algorithm 2:
  :meth:`Policy.plan` ``(xi, x, u_prev, generator, **sampler) -> (B, n, A)``, the actions to play from ``x``
  in ``policy.task.action`` units, of which a rollout plays ``T_a <= max_t_a`` before planning again, with the
  sampler keywords :meth:`Policy.sampler_options` validates (``k_rollout`` for diffusion families). A per-step
  family (the MLPs) plans one control (``n = max_t_a = 1``, action ``u``); a chunked one (:class:`ChunkPlanning`)
  the rows of its chunk after the observed ones (``n = max_t_a = T_h - T_o``).

A family is one module with a subclass and one :func:`~sdp_cli.policy.registry.register_method`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch
from torch import nn
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.base import check_task_params

if TYPE_CHECKING:
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.tasks import Task


def as_tensor(a, device) -> torch.Tensor:
    """float32 tensor on ``device`` from an array or tensor."""
    return torch.as_tensor(np.asarray(a, dtype=np.float64) if not torch.is_tensor(a) else a,
                           device=device).to(torch.float32)


class ChunkPlanning:
    """The action API of a chunked planner with ``T_h``, ``T_o``, ``K`` and ``predict_chunk(xi, x, u_prev,
    generator, k_rollout) -> (B, T_h, A)`` (rows ``[:T_o]`` the observed history): :meth:`plan` is the rows
    after the history. Used by the diffusion families and by the memorizer (sdp_cli.policy.memorizer)."""

    @property
    def max_t_a(self) -> int:
        """``T_h - T_o``: the rows a chunk plans after the observed ones (T_a's bound and default)."""
        return self.T_h - self.T_o

    def sampler_options(self, k_rollout: int | None = None) -> dict:
        """``{"k_rollout": k}`` with ``k`` in ``[1, K]`` (default ``K``), else a one-line ``SdpError``."""
        k = self.K if k_rollout is None else int(k_rollout)
        if not 1 <= k <= self.K:
            raise SdpError(f"k_rollout must be in [1, K] = [1, {self.K}], got {k}")
        return {"k_rollout": k}

    def plan(self, xi, x, u_prev, generator=None, **sampler) -> np.ndarray:
        """``(B, T_h - T_o, A)``: the predicted chunk's rows after the observed history."""
        return self.predict_chunk(xi, x, u_prev, generator=generator, **sampler)[:, self.T_o:]


class Policy(nn.Module):
    """Base of every policy family (see the module docstring). Subclasses set :attr:`chunked` and build
    ``self.normalizer`` and their network in ``__init__(config, dims)``."""

    #: plans chunks of ``T_h`` actions from ``(x, u_prev, xi)`` (Algorithm 2: ``predict_chunk``) rather
    #: than one control per state (``act``); rollouts, ``T_a`` options and the estimate follow it
    chunked: ClassVar[bool] = False
    #: the family can train several runs as one stacked network (:mod:`sdp_cli.training.train_stack`; ``sdp pipeline
    #: --run --stack``): it then gives ``stack(policies)`` (one module with ``parameters``, ``zero_grad`` and
    #: ``losses(draws)``) and ``draw(batch, generator)``; a family opts in, the others train each run alone
    stackable: ClassVar[bool] = False
    #: the family compiles its network for training when the config says ``compile`` (:meth:`compile_network`)
    compilable: ClassVar[bool] = False

    def __init__(self, config: TrainConfig, dims: dict):
        super().__init__()
        self.config = config
        self.dims = {k: int(v) for k, v in dims.items()}
        #: factor of the Sobolev term on the training data (:func:`sdp_cli.losses.sobolev.balance_scale`),
        #: set by the trainer before the first step; 1 elsewhere
        self.sobolev_scale = 1.0
        self.task: Task | None = None     # set by bind()

    # ------------------------------------------------------------------ data
    @classmethod
    def make_dataset(cls, config: TrainConfig, task: Task, arrays: dict, with_jacobians: bool):
        """``(dataset, action)``: the family's training samples of a TO dataset (``.tensors(normalizer,
        device)``, ``.epoch_size()``) and the action variable the network predicts."""
        raise NotImplementedError

    @classmethod
    def action_for(cls, config: TrainConfig, task: Task) -> str:
        """The action variable the network predicts on ``task`` (what :meth:`make_dataset` returns beside its
        dataset): the config's ``action``, else the task's."""
        return config.policy.action or task.action

    @classmethod
    def dims_for(cls, config: TrainConfig, task: Task, action: str) -> dict:
        """Network sizes ``{n_action, n_obs, n_xi, ndx}``."""
        raise NotImplementedError

    def compile_network(self) -> None:
        """Compile the network's training calls (``TrainConfig.compile``; a family that sets :attr:`compilable`
        implements it); the trainer calls it once before the first step. Weights and state dict stay the same."""
        raise NotImplementedError

    # ------------------------------------------------------------------ configuration
    @classmethod
    def check_config(cls, config: TrainConfig) -> None:
        """The family's own rules on a training config (one ``SdpError`` naming the option), after the rules
        every option obeys (:func:`sdp_cli.policy.config.check`); e.g. the U-Net's divisibility rules."""

    @classmethod
    def sampler_steps(cls, config: TrainConfig) -> int | None:
        """Network calls of the family's sampler per plan at most (``k_rollout``'s bound and default: the
        diffusion steps K), or None: no sampler, one network call per plan."""
        return None

    # ------------------------------------------------------------------ training
    def compute_loss(self, batch: dict, generator: torch.Generator | None = None):
        """``(loss, {"dp": regression term, "sobolev": scaled Sobolev term})`` of a normalized batch."""
        raise NotImplementedError

    def balance_terms(self, tensors: dict):
        """``(targets, jacobians)`` of the Sobolev balance on the whole training set."""
        raise NotImplementedError

    @property
    def method(self) -> str:
        return self.config.method

    # ------------------------------------------------------------------ the action API (Algorithm 2)
    # (defaults: a chunked family with ``predict_chunk``, ``T_h``, ``T_o``, ``K`` plans as :class:`ChunkPlanning`;
    # a per-step family with ``act(x, xi) -> (B, nu)`` plans one control)
    @property
    def max_t_a(self) -> int:
        """How many of :meth:`plan`'s rows a rollout may play before planning again (T_a's bound and default);
        1 for a per-step family."""
        return ChunkPlanning.max_t_a.fget(self) if self.chunked else 1

    def sampler_options(self, k_rollout: int | None = None) -> dict:
        """The validated sampler keywords of :meth:`plan`; a family without a sampler takes none."""
        if self.chunked and type(self).sampler_steps(self.config) is not None:   # the family declares a sampler
            return ChunkPlanning.sampler_options(self, k_rollout)
        if k_rollout is not None:
            raise SdpError(f"k_rollout (denoising steps at rollout) applies to diffusion policies; "
                           f"{self.method!r} has no sampler")
        return {}

    def plan(self, xi, x, u_prev, generator=None, **sampler) -> np.ndarray:
        """The actions to play from the states ``x (B, nx)``: ``(B, n, A)`` with ``n >= max_t_a``, in
        ``policy.task.action`` units (``xi (B, n_xi)``, ``u_prev (B, nu)`` the previous controls)."""
        if self.chunked:
            return ChunkPlanning.plan(self, xi, x, u_prev, generator, **sampler)
        return self.act(x, xi)[:, None]

    # ------------------------------------------------------------------ rollout
    def bind(self, ck: dict, device="cpu") -> "Policy":
        """Attach the checkpoint's task (checked against its recorded identity) and metadata; move to
        ``device`` in eval mode. Returns self."""
        from sdp_cli.data.chunks import task_with_action

        self.device = torch.device(device)
        self.action = ck["action"]
        self.task_name = ck["task"]
        self.task_options: dict = dict(ck.get("task_options") or {})   # recorded by rollouts, checked by refine
        task = get_task(ck["task"], **self.task_options)
        check_task_params(task, ck.get("task_params"), "policy checkpoint")
        # the policy's action variable (a per-step family's is ``u``) may differ from the task's default
        self.task = task_with_action(task, self.action)
        self.checkpoint_epoch = ck.get("epoch")
        self.dataset_info = dict(ck.get("dataset") or {})   # path, sha256, n_traj, T of the training data
        return self.to(self.device).eval()

    @property
    def norm(self):
        return self.normalizer

    def _obs(self, x: np.ndarray, u_prev: np.ndarray) -> torch.Tensor:
        """Normalized ``o = (obs(x), u_prev)``: (..., nx), (..., nu) -> (..., n_o)."""
        o = np.concatenate([self.task.observation(np.asarray(x, float)), np.asarray(u_prev, float)], -1)
        return self.normalizer.normalize("obs", as_tensor(o, self.device))

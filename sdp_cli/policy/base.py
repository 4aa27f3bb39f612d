"""The policy object every method family implements (after lerobot's ``PreTrainedPolicy``).

A policy is one ``nn.Module`` that owns its configuration (:class:`~sdp_cli.policy.config.TrainConfig`),
its normalizer (:class:`~sdp_cli.data.normalizer.Normalizer`, a submodule: its ranges travel in the
state dict), its network (a bare ``nn.Module`` such as the U-Net) and, for diffusion, its noise
scheduler. Everything the project does with a policy goes through this interface:

- **data** (class methods, before a policy exists): :meth:`Policy.make_dataset` cuts a TO dataset into
  the family's samples and names the action variable; :meth:`Policy.dims_for` gives the network sizes;
- **training** (normalized tensors): :meth:`Policy.compute_loss` ``(batch, generator) -> (loss, parts)``
  with ``parts = {"dp": regression, "sobolev": term}``; :meth:`Policy.balance_terms` feeds the Sobolev
  balance; :func:`sdp_cli.train.train_step` is the one optimisation step (trainer and estimate);
- **rollout** (physical units, numpy, batched): after :meth:`Policy.bind` (done by
  :func:`~sdp_cli.policy.api.load_policy`), chunked families answer ``predict_chunk(xi, x, u_prev)``
  ``-> (B, T_h, A)`` and the others ``act(x, xi) -> (B, nu)``.

A family is one module with a subclass and one :func:`~sdp_cli.policy.registry.register_method`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch
from torch import nn

if TYPE_CHECKING:
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.tasks import Task


def as_tensor(a, device) -> torch.Tensor:
    """float32 tensor on ``device`` from an array or tensor."""
    return torch.as_tensor(np.asarray(a, dtype=np.float64) if not torch.is_tensor(a) else a,
                           device=device).to(torch.float32)


class Policy(nn.Module):
    """Base of every policy family (see the module docstring). Subclasses set :attr:`chunked` and build
    ``self.normalizer`` and their network in ``__init__(config, dims)``."""

    #: plans chunks of ``T_h`` actions from ``(x, u_prev, xi)`` (Algorithm 2: ``predict_chunk``) rather
    #: than one control per state (``act``); rollouts, ``T_a`` options and the estimate follow it
    chunked: ClassVar[bool] = False

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
    def dims_for(cls, config: TrainConfig, task: Task, action: str) -> dict:
        """Network sizes ``{n_action, n_obs, n_xi, ndx}``."""
        raise NotImplementedError

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

    @property
    def is_diffusion(self) -> bool:
        """Chunked (Algorithm 2) rather than one control per state (the name the rollout code reads)."""
        return self.chunked

    # ------------------------------------------------------------------ rollout
    def bind(self, ck: dict, device="cpu") -> "Policy":
        """Attach the checkpoint's task (checked against its recorded identity) and metadata; move to
        ``device`` in eval mode. Returns self."""
        from sdp_cli.data.chunks import task_with_action
        from sdp_cli.tasks import get_task
        from sdp_cli.tasks.base import check_task_params

        self.device = torch.device(device)
        self.action = ck["action"]
        self.task_name = ck["task"]
        self.task_options: dict = dict(ck.get("task_options") or {})   # recorded by rollouts, checked by refine
        task = get_task(ck["task"], **self.task_options)
        check_task_params(task, ck.get("task_params"), "policy checkpoint")
        # a chunked policy's action variable may differ from the task's default
        self.task = task_with_action(task, self.action) if self.chunked else task
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

"""Configuration of a policy and of its training run (stored in full in every checkpoint)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from sdp_cli.errors import SdpError

SOBOLEV_MODES = ("jvp", "vjp")
SOBOLEV_PATHS = ("cond", "total")


@dataclass
class TrainConfig:
    """Everything that defines a training run (defaults follow the paper / diffusion policy)."""

    method: str = "sdp"
    epochs: int = 1000
    seed: int = 0
    batch_size: int = 256
    # diffusion model
    T_h: int = 32
    T_o: int = 1
    K: int = 5                       # diffusion steps (train); K_rollout <= K at inference
    down_dims: list = field(default_factory=lambda: [24, 24, 32, 32])
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 64
    clip_sample: bool = True
    action: str | None = None        # None: the task's action variable
    # MLP baselines
    mlp_hidden: list = field(default_factory=lambda: [256, 256, 256])
    # Sobolev term
    alpha_sobolev: float | None = None  # None: the task's default (paper: 1, quadrotor 1e-3)
    sobolev_balance: bool = True      # scale the Sobolev term so that alpha = 1 weighs both terms
                                      # equally on the dataset (losses.sobolev.balance_scale)
    sobolev_path: str = "cond"        # "cond": d/dx through (o_hist, a_hist) only; "total": also
                                      # through the noisy chunk tau_k (sqrt(alpha_bar_k) J)
    n_proj: int = 1
    sobolev_mode: str = "jvp"        # "jvp": projection on the x side (forward mode); "vjp": eq. (6)
    sobolev_fraction: float = 1.0    # jvp mode: share of each batch that gets the Sobolev term
    sobolev_cap: float | None = None  # quantile of the chunk-Jacobian norms above which the Sobolev
                                      # error is down-weighted (losses.sobolev.capped_weights); None: off
    # optimization (diffusion policy defaults)
    lr: float = 1e-3
    weight_decay: float = 1e-6
    betas: tuple = (0.95, 0.999)
    warmup_steps: int | None = None  # None: min(500, total_steps // 10)
    grad_clip: float = 1.0
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    # bookkeeping
    save_at: list = field(default_factory=list)   # epochs at which to keep a checkpoint
    checkpoint_every_s: float = 60.0

    def __post_init__(self):
        from sdp_cli.policy.registry import get_method

        get_method(self.method)   # a registered method (sdp_cli.policy.registry), else one clear error
        from sdp_cli.seeds import check_seed

        check_seed(self.seed)
        if self.sobolev_mode not in SOBOLEV_MODES:
            raise SdpError(f"sobolev mode must be one of {', '.join(SOBOLEV_MODES)}; got {self.sobolev_mode!r}")
        for name in ("epochs", "batch_size", "K", "n_proj", "T_h", "T_o"):
            if getattr(self, name) <= 0:
                raise SdpError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.checkpoint_every_s < float("inf"):
            raise SdpError(f"checkpoint_every_s must be >= 0, got {self.checkpoint_every_s}")
        for name in ("lr", "grad_clip", "ema_max_decay"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0 and v == v and v != float("inf")):
                raise SdpError(f"{name} must be a finite number > 0, got {v}")
        if not 0 <= self.weight_decay < float("inf"):
            raise SdpError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if not self.ema_max_decay <= 1:
            raise SdpError(f"ema_max_decay must be in (0, 1], got {self.ema_max_decay}")
        if not (len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas)):
            raise SdpError(f"betas must be two numbers in [0, 1), got {list(self.betas)}")
        if self.warmup_steps is not None and self.warmup_steps < 0:
            raise SdpError(f"warmup_steps must be >= 0, got {self.warmup_steps}")
        if any(not 0 < int(e) < self.epochs for e in self.save_at):
            raise SdpError(f"save_at epochs must be in (0, epochs = {self.epochs}), got {list(self.save_at)}")
        if not 0 < self.sobolev_fraction <= 1:
            raise SdpError(f"sobolev_fraction must be in (0, 1], got {self.sobolev_fraction}")
        if self.sobolev_fraction < 1 and self.sobolev_mode != "jvp":
            raise SdpError("sobolev_fraction < 1 needs sobolev_mode 'jvp'")
        if self.sobolev_path not in SOBOLEV_PATHS:
            raise SdpError(f"sobolev path must be one of {', '.join(SOBOLEV_PATHS)}; got {self.sobolev_path!r}")
        if self.sobolev_path == "total" and not (self.is_diffusion and self.sobolev):
            raise SdpError(f"sobolev_path 'total' applies to Sobolev diffusion methods (sdp), not {self.method!r}")
        if self.alpha_sobolev is not None and not 0 <= self.alpha_sobolev < float("inf"):
            raise SdpError(f"alpha_sobolev must be >= 0, got {self.alpha_sobolev}")
        if self.sobolev_cap is not None:
            if not 0 < self.sobolev_cap <= 1:
                raise SdpError(f"sobolev_cap is a quantile in (0, 1], got {self.sobolev_cap}")
            if not (self.is_diffusion and self.sobolev):
                raise SdpError(f"sobolev_cap applies to Sobolev diffusion methods (sdp), not {self.method!r}")
        if self.is_diffusion:
            levels = len(self.down_dims)
            if self.T_h % (2 ** (levels - 1)):
                raise SdpError(f"T_h = {self.T_h} must be divisible by 2^(len(down_dims) - 1) = "
                               f"{2 ** (levels - 1)} for the U-Net")
            bad = [d for d in self.down_dims if d % self.n_groups]
            if bad:
                raise SdpError(f"down_dims {bad} not divisible by n_groups = {self.n_groups}")
        self.down_dims = [int(d) for d in self.down_dims]
        self.mlp_hidden = [int(d) for d in self.mlp_hidden]
        self.betas = tuple(float(b) for b in self.betas)
        self.save_at = sorted(int(e) for e in self.save_at)

    @property
    def policy_class(self):
        """The method's policy class (:mod:`sdp_cli.policy.registry`): data, network, loss, sampling."""
        from sdp_cli.policy.registry import get_method

        return get_method(self.method).policy_class

    @property
    def is_diffusion(self) -> bool:
        """A chunked (diffusion) method: plans action chunks, Algorithm 2."""
        from sdp_cli.policy.registry import get_method

        return get_method(self.method).chunked

    @property
    def sobolev_weight(self) -> float:
        """alpha_Sobolev as the losses use it (None, the task's default, is resolved by ``train``; 1 outside it)."""
        return 1.0 if self.alpha_sobolev is None else float(self.alpha_sobolev)

    @property
    def sobolev(self) -> bool:
        from sdp_cli.policy.registry import get_method

        return get_method(self.method).sobolev

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

"""Configuration of a policy and of its training run: typed sections, stored in full in every checkpoint.

::

    TrainConfig
      policy:  PolicyConfig   method and architecture: what rebuilds the network
      data:    DataConfig     epochs, batch size
      optim:   OptimConfig    AdamW, LR warm-up, gradient clipping, EMA
      sobolev: SobolevConfig  the first-order term (eq. 4 / 6)
      seed, save_at, checkpoint_every_s

Every field is a training *option* with one name (:func:`options`): the field's name, or ``sobolev_<field>``
in the ``sobolev`` section (``sobolev.alpha`` is ``sobolev_alpha``). That name is the flag of ``sdp train``
and ``sdp loop`` (``--horizon``, ``--sobolev-alpha``; both commands get their training options from here,
:func:`sdp_cli.cli_options.with_train_options`), the key of an experiment group's ``train:`` mapping (its
type checked against the field's) and so the DVC parameter (``groups.G.train.sobolev_alpha``). A new option
is one field here (with its ``help``) plus the code that reads it. The paper's symbols: ``horizon`` is T_h,
``n_obs_steps`` T_o, ``diffusion_steps`` K, ``sobolev_alpha`` alpha_Sobolev.

Checkpoints and loop folders written before the sections existed store one flat dict with other names
(``T_h``, ``K``, ``alpha_sobolev``, ...): :func:`TrainConfig.from_dict` migrates them (:data:`RENAMED`).
"""

from __future__ import annotations

from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from typing import Any, get_type_hints
import types
import typing

from sdp_cli.errors import SdpError
from sdp_cli.rules import check_fields, rule
from sdp_cli.policy.registry import get_method
from sdp_cli.seeds import check_seed

SOBOLEV_MODES = ("jvp", "vjp")
SOBOLEV_PATHS = ("cond", "total")


def opt(default=MISSING, help: str = "", factory=MISSING, **bounds):
    """A config field that is a training option (its ``help`` is the flag's); ``bounds`` (``ge=1``, ``gt=0``,
    ``le=1``, ``lt=1``, ``odd=True``) its range (:mod:`sdp_cli.rules`: finite, and each item of a list)."""
    meta = {"help": help, **(rule(**bounds) if bounds else {})}
    if factory is not MISSING:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class PolicyConfig:
    """The method and its architecture (everything :func:`~sdp_cli.policy.registry.make_policy` needs)."""

    method: str = opt("sdp", "Method (a registered policy family).")
    action: str | None = opt(None, "Action variable u, x, q or v (default: the task's).")
    horizon: int = opt(32, "Chunk length T_h (chunked methods).", ge=1)
    n_obs_steps: int = opt(1, "Observed steps T_o (chunked methods).", ge=1)
    diffusion_steps: int = opt(5, "DDPM steps K (training; rollouts may use fewer).", ge=1)
    down_dims: list[int] = opt(help="U-Net channels per level, comma-separated.", factory=lambda: [24, 24, 32, 32], ge=1)
    kernel_size: int = opt(5, "U-Net convolution kernel size (odd: the chunk keeps its length).", ge=1, odd=True)
    n_groups: int = opt(8, "GroupNorm groups of the U-Net.", ge=1)
    step_embed_dim: int = opt(64, "Diffusion-step embedding size.", ge=2)
    clip_sample: bool = opt(True, "Clip denoised chunks to [-1, 1] (normalized units).")
    mlp_hidden: list[int] = opt(help="Hidden layer sizes of the MLP baselines, comma-separated.",
                                factory=lambda: [256, 256, 256], ge=1)

    @property
    def max_t_a(self) -> int:
        """``T_h - T_o``: the rows a chunk plans after its observed ones, the largest T_a of a chunked
        policy and T_a's default (Algorithm 2; every module that needs the default asks here)."""
        return self.horizon - self.n_obs_steps


@dataclass
class DataConfig:
    """How much of the dataset a run sees (Sec. IV's epochs; :mod:`sdp_cli.data.sampling`)."""

    epochs: int = opt(1000, "Epochs (per iteration of `sdp loop`): |D|(T-T_h)/T_h chunks (diffusion) or |D|T "
                                   "pairs (MLP) each.", ge=1)
    batch_size: int = opt(256, "Batch size B.", ge=1)


@dataclass
class OptimConfig:
    """AdamW, cosine learning rate with linear warm-up, clipping and EMA (diffusion policy's defaults)."""

    lr: float = opt(1e-3, "Peak AdamW learning rate (cosine schedule with warm-up).", gt=0)
    weight_decay: float = opt(1e-6, "AdamW weight decay.", ge=0)
    betas: list[float] = opt(help="AdamW betas, comma-separated.", factory=lambda: [0.95, 0.999], ge=0, lt=1)
    warmup_steps: int | None = opt(None, "Linear LR warm-up steps (default: min(500, total steps / 10)).", ge=0)
    grad_clip: float = opt(1.0, "Gradient-norm clip.", gt=0)
    ema_power: float = opt(0.75, "EMA warm-up power.", gt=0)
    ema_max_decay: float = opt(0.9999, "EMA maximum decay.", gt=0, le=1)


@dataclass
class SobolevConfig:
    """The Sobolev term (Sec. III): its weight, balance and how the Jacobian is matched."""

    alpha: float | None = opt(None, "Weight alpha_Sobolev of the Sobolev term (default: the task's, the paper's "
                                    "values: 1, quadrotor 1e-3).", ge=0)
    balance: bool = opt(True, "Scale the Sobolev term so that alpha 1 weighs it equally with the regression term "
                              "on the dataset (docs/training.md).")
    path: str = opt("cond", "sdp: cond = differentiate through (o_hist, a_hist) only; total = also through the "
                            "noisy chunk tau_k.")
    n_proj: int = opt(1, "Random projections per sample.", ge=1)
    mode: str = opt("jvp", "jvp: project on the state side (forward mode); vjp: eq. (6), project on the output side.")
    fraction: float = opt(1.0, "jvp mode: share of each batch that gets the Sobolev term (1 = all; 0.5 costs "
                               "~1.5x a DP step instead of ~1.9x).", gt=0, le=1)
    cap: float | None = opt(None, "sdp: down-weight the Sobolev error of chunks whose target-Jacobian norm "
                                  "exceeds this quantile of the dataset's (e.g. 0.9); off by default.", gt=0, le=1)

    @property
    def weight(self) -> float:
        """alpha as the losses use it (None, the task's default, is resolved by ``train``; 1 outside it)."""
        return 1.0 if self.alpha is None else float(self.alpha)


SECTIONS = {"policy": PolicyConfig, "data": DataConfig, "optim": OptimConfig, "sobolev": SobolevConfig}
PREFIXED = ("sobolev",)   # sections whose option names carry the section's name


@dataclass
class TrainConfig:
    """Everything that defines a training run (see the module docstring)."""

    policy: PolicyConfig = field(default_factory=PolicyConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    sobolev: SobolevConfig = field(default_factory=SobolevConfig)
    seed: int = opt(0, "Seed of initialization, batches, noise and projections (`sdp loop`: also of collection, "
                        "1000 * seed + k).")
    save_at: list[int] = opt(help="Epochs at which to keep a checkpoint too, comma-separated, e.g. 1000 (`sdp loop` "
                                  "evaluates them too: Fig. 1).",
                             factory=list, ge=1)
    checkpoint_every_s: float = opt(60.0, "Seconds between checkpoints of the run (and at the end, on Ctrl-C).", ge=0)
    compile: bool = opt(False, "torch.compile (inductor) the network's forward and tangent pass for training: "
                               "about 1.5x faster SDP steps on a CPU after a one-off compile of minutes (seconds "
                               "with a warm cache, $SDP_COMPILE_CACHE); numerics differ from eager at float32 "
                               "rounding, recorded in the checkpoint (docs/training.md).")

    def __post_init__(self):
        self.policy.down_dims = [int(d) for d in self.policy.down_dims]
        self.policy.mlp_hidden = [int(d) for d in self.policy.mlp_hidden]
        self.optim.betas = [float(b) for b in self.optim.betas]
        self.save_at = sorted(int(e) for e in self.save_at)
        check(self)

    # ------------------------------------------------------------------ what the method is
    @property
    def method(self) -> str:
        return self.policy.method

    @property
    def policy_class(self):
        """The method's policy class (:mod:`sdp_cli.policy.registry`): data, network, loss, sampling."""
        return get_method(self.method).policy_class

    @property
    def chunked(self) -> bool:
        """A chunked method: plans action chunks, Algorithm 2 (the method's registration says so)."""
        return get_method(self.method).chunked

    @property
    def uses_sobolev(self) -> bool:
        """The method trains with the Sobolev term (needs the dataset's gains)."""
        return get_method(self.method).sobolev

    # ------------------------------------------------------------------ options and storage
    @classmethod
    def of(cls, **opts) -> "TrainConfig":
        """The config of these options (flat names, :func:`options`); the others at their defaults."""
        unknown = sorted(set(opts) - set(options()))
        if unknown:
            hint = "; ".join(f"{k} is now {RENAMED[k]}" for k in unknown if k in RENAMED)
            raise SdpError(f"unknown training option(s) {unknown}" + (f" ({hint})" if hint else ""))
        parts: dict[str, dict] = {s: {} for s in SECTIONS}
        top = {}
        for name, value in opts.items():
            section, fname = options()[name]
            (parts[section] if section else top)[fname] = value
        return cls(**{s: SECTIONS[s](**parts[s]) for s in SECTIONS}, **top)

    def options(self) -> dict[str, Any]:
        """``{option name: value}`` of every option (the inverse of :meth:`of`)."""
        return {name: getattr(getattr(self, s) if s else self, f) for name, (s, f) in options().items()}

    def with_options(self, **opts) -> "TrainConfig":
        return TrainConfig.of(**{**self.options(), **opts})

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """From :meth:`to_dict`'s nested dict, or the flat dict of checkpoints before the sections (migrated)."""
        return cls.of(**flat_options(d))

    def architecture(self) -> dict:
        """The policy section as options (what an ``--init`` checkpoint imposes)."""
        return {name: v for name, v in self.options().items() if options()[name][0] == "policy"}


#: flat names of checkpoints and loop folders before the sections (format_version 1) -> option names
RENAMED = {"T_h": "horizon", "T_o": "n_obs_steps", "K": "diffusion_steps", "alpha_sobolev": "sobolev_alpha",
           "n_proj": "sobolev_n_proj"}


def flat_options(d: dict) -> dict:
    """``{option: value}`` of a stored config: nested (:meth:`TrainConfig.to_dict`) or flat (older
    checkpoints, whose names :data:`RENAMED` maps); keys no option has are dropped."""
    if any(isinstance(d.get(s), dict) for s in SECTIONS):
        out = {}
        for name, (s, f) in options().items():
            src = d.get(s) if s else d
            if isinstance(src, dict) and f in src:
                out[name] = src[f]
        return out
    known = options()
    renamed = {RENAMED.get(k, k): v for k, v in d.items()}
    return {k: v for k, v in renamed.items() if k in known}


def options() -> dict[str, tuple[str | None, str]]:
    """``{option name: (section or None, field)}`` of every training option, in declaration order."""
    global _OPTIONS
    if _OPTIONS is None:
        out = {}
        for f in fields(TrainConfig):
            if f.name in SECTIONS:
                for sf in fields(SECTIONS[f.name]):
                    out[f"{f.name}_{sf.name}" if f.name in PREFIXED else sf.name] = (f.name, sf.name)
            else:
                out[f.name] = (None, f.name)
        _OPTIONS = out
    return _OPTIONS


_OPTIONS = None


def option_field(name: str):
    """``(type, default, help)`` of an option: its annotation (``int | None``, ``list[int]``, ...), its default
    value and its help text."""
    section, fname = options()[name]
    cls = SECTIONS[section] if section else TrainConfig
    f = {x.name: x for x in fields(cls)}[fname]
    default = f.default_factory() if f.default_factory is not MISSING else f.default
    return get_type_hints(cls)[fname], default, f.metadata.get("help", "")


def option_type(name: str) -> tuple[type, type | None, bool]:
    """``(type, item type, optional)`` of an option's annotation: ``int | None`` -> ``(int, None, True)``,
    ``list[int]`` -> ``(list, int, False)``."""
    ann = option_field(name)[0]
    optional = typing.get_origin(ann) in (typing.Union, types.UnionType)
    base = next(a for a in typing.get_args(ann) if a is not type(None)) if optional else ann
    if typing.get_origin(base) is list:
        return list, typing.get_args(base)[0], optional
    return base, None, optional


def check(cfg: TrainConfig) -> None:
    """Every rule a config obeys (one :class:`SdpError` naming the option)."""
    p, o, s = cfg.policy, cfg.optim, cfg.sobolev
    get_method(p.method)   # a registered method (sdp_cli.policy.registry), else one clear error
    check_seed(cfg.seed)
    if any(not 0 < int(e) < cfg.data.epochs for e in cfg.save_at):
        raise SdpError(f"save_at epochs must be in (0, epochs = {cfg.data.epochs}), got {list(cfg.save_at)}")
    for section in SECTIONS:   # each option's own range, declared on its field (finite, in range)
        check_fields(getattr(cfg, section), prefix=f"{section}_" if section in PREFIXED else "")
    check_fields(cfg)
    if s.mode not in SOBOLEV_MODES:
        raise SdpError(f"sobolev_mode must be one of {', '.join(SOBOLEV_MODES)}; got {s.mode!r}")
    if len(o.betas) != 2:
        raise SdpError(f"betas must be two numbers in [0, 1), got {list(o.betas)}")
    if s.fraction < 1 and s.mode != "jvp":
        raise SdpError("sobolev_fraction < 1 needs sobolev_mode 'jvp'")
    if s.path not in SOBOLEV_PATHS:
        raise SdpError(f"sobolev_path must be one of {', '.join(SOBOLEV_PATHS)}; got {s.path!r}")
    sobolev_diffusion = cfg.chunked and cfg.uses_sobolev
    if s.path == "total" and not sobolev_diffusion:
        raise SdpError(f"sobolev_path 'total' applies to Sobolev diffusion methods (sdp), not {p.method!r}")
    if s.cap is not None:
        if not sobolev_diffusion:
            raise SdpError(f"sobolev_cap applies to Sobolev diffusion methods (sdp), not {p.method!r}")
    for name in ("down_dims", "mlp_hidden"):
        if not getattr(p, name):
            raise SdpError(f"{name} must be positive integers, got {getattr(p, name)}")
    if cfg.compile and not getattr(cfg.policy_class, "compilable", False):
        raise SdpError(f"compile: the {p.method!r} family does not compile its network (train it without --compile)")
    cfg.policy_class.check_config(cfg)   # the family's own rules (the U-Net's, for the diffusion methods)


def resolved_alpha(cfg: TrainConfig, task) -> TrainConfig:
    """``cfg`` with ``sobolev.alpha`` None replaced by the task's default (:attr:`Task.sobolev_alpha`)."""
    if cfg.sobolev.alpha is not None:
        return cfg
    return replace(cfg, sobolev=replace(cfg.sobolev, alpha=float(task.sobolev_alpha)))

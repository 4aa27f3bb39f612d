"""Training options are declared once, as TrainConfig fields, and mean the same everywhere: every `sdp train`
option names a field, `sdp loop` forwards its training options under the same flags as `sdp train`, and the
experiment files' `train:` keys are exactly the fields a group does not set itself."""

from __future__ import annotations

from dataclasses import fields

import typer

from sdp_cli.cli import app
from sdp_cli.pipeline import _GROUP_OWNED, train_option_names
from sdp_cli.policy.config import TrainConfig

#: `sdp train` parameters that are not TrainConfig fields (where the run goes, how it runs) and the
#: ones whose CLI name differs from the field
NOT_CONFIG = {"data", "out", "device", "resume", "init", "threads", "progress"}
RENAMED = {"horizon": "T_h", "diffusion_steps": "K"}


def _params(command: str) -> dict:
    cmd = typer.main.get_command(app).commands[command]
    return {p.name: p for p in cmd.params}


def test_every_train_option_is_a_config_field():
    names = {f.name for f in fields(TrainConfig)}
    for name in _params("train"):
        if name not in NOT_CONFIG:
            assert RENAMED.get(name, name) in names, f"`sdp train` option {name} is no TrainConfig field"


def test_loop_and_pipeline_pass_train_options_under_the_same_flags():
    """`sdp loop` has every `sdp train` training option that is not one of its own (generated from `sdp train`'s
    declarations: the same flags, default None = TrainConfig's default), and nothing else of `sdp train`'s."""
    train, loop = _params("train"), _params("loop")
    names = {f.name for f in fields(TrainConfig)}
    assert train_option_names() == names - _GROUP_OWNED      # pipelines/*.yaml `train: {field: value}`
    assert _GROUP_OWNED <= names
    loop_own = {"method", "epochs", "seed", "horizon", "save_at", "device", "threads", "progress", "out"}
    forwarded = {n for n in train if n not in NOT_CONFIG and n not in loop_own}
    assert forwarded == {"batch_size", "lr", "diffusion_steps", "down_dims", "alpha_sobolev", "sobolev_balance",
                         "sobolev_path", "n_proj", "sobolev_mode", "sobolev_fraction", "sobolev_cap", "action"}
    for key in forwarded:
        assert key in loop, key
        assert loop[key].opts == train[key].opts and loop[key].secondary_opts == train[key].secondary_opts, key
        assert loop[key].default is None, key
        assert RENAMED.get(key, key) in names, key       # and each is a TrainConfig field


def test_shared_options_are_declared_once():
    """--workers/--executor/--scheduler (solves), --device, --threads and --progress mean the same in every
    command that has them (one Annotated alias each in sdp_cli.cli)."""
    groups = {"workers": ("collect", "refine", "loop"), "executor": ("collect", "refine", "loop"),
              "scheduler": ("collect", "refine", "loop"), "device": ("train", "rollout", "loop"),
              "threads": ("collect", "train", "rollout", "loop"), "progress": ("collect", "refine", "train", "loop"),
              "to": ("collect", "refine", "loop")}
    for opt, commands in groups.items():
        decls = {(tuple(_params(c)[opt].opts), _params(c)[opt].help, _params(c)[opt].default) for c in commands}
        assert len(decls) == 1, (opt, decls)

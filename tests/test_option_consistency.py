"""Training options are declared for the TrainConfig dataclass and must mean the same everywhere:
every option `sdp loop` and the experiment files (pipelines/*.yaml `train:`) pass on to training is an
`sdp train` option with the same flag, naming a TrainConfig field."""

from __future__ import annotations

from dataclasses import fields

import typer

from sdp_cli.cli import app
from sdp_cli.pipeline import _TRAIN_FLAGS
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
    train = {opt for p in _params("train").values() for opt in p.opts + p.secondary_opts}
    loop = _params("loop")
    names = {f.name for f in fields(TrainConfig)}
    for key, flag in _TRAIN_FLAGS.items():        # pipelines/*.yaml `train: {key: value}`
        assert RENAMED.get(key, key) in names, key
        assert flag in train, f"pipeline train option {key} uses {flag}, which `sdp train` does not have"
    for key in ("alpha_sobolev", "batch_size", "sobolev_cap", "sobolev_path", "sobolev_balance"):
        assert key in loop and key in names          # `sdp loop` forwards these into TrainConfig
        assert set(loop[key].opts) <= train, key

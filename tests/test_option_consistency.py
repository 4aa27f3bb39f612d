"""Training options are declared once, as fields of the typed TrainConfig sections, and mean the same
everywhere: `sdp train` and `sdp loop` get every option under the same flag (generated, not hand-listed), an
experiment group's `train:` takes every option the group does not set itself, with the field's type, and the
stored configs of older checkpoints and loop folders migrate to the same options."""

from __future__ import annotations

import json

import pytest
import typer

from sdp_cli.cli import app
from sdp_cli.errors import SdpError
from sdp_cli.experiments.pipeline import _GROUP_OWNED, train_option_names, train_option_type
from sdp_cli.policy.config import RENAMED, TrainConfig, flat_options, options

#: `sdp train` parameters that are not training options (where the run goes, how it runs)
NOT_CONFIG = {"data", "out", "device", "resume", "init", "threads", "progress"}


def _params(command: str) -> dict:
    cmd = typer.main.get_command(app).commands[command]
    return {p.name: p for p in cmd.params}


def test_every_training_option_is_a_flag_of_train_and_loop_under_one_name():
    train, loop = _params("train"), _params("loop")
    assert set(train) - NOT_CONFIG == set(options())
    assert set(options()) <= set(loop)
    for name in options():
        assert train[name].opts == loop[name].opts == ["--" + name.replace("_", "-")], name
        assert train[name].help == loop[name].help and train[name].help, name
        assert train[name].default is None and loop[name].default is None, name    # None: the config's default
    assert train["method"].required and loop["method"].required
    assert "T_h" not in options() and "K" not in options()      # one name per quantity: horizon, diffusion_steps


def test_experiment_train_keys_are_the_options_a_group_does_not_own():
    assert _GROUP_OWNED <= set(options())
    assert train_option_names() == set(options()) - _GROUP_OWNED
    assert {n: train_option_type(n) for n in ("down_dims", "betas", "sobolev_alpha", "clip_sample", "warmup_steps")} \
        == {"down_dims": "[int]", "betas": "[float]", "sobolev_alpha": "float?", "clip_sample": "bool",
            "warmup_steps": "int?"}


def test_options_round_trip_and_older_flat_configs_migrate():
    cfg = TrainConfig.of(method="sdp", horizon=16, diffusion_steps=10, sobolev_alpha=0.5, sobolev_n_proj=2,
                         lr=3e-4, down_dims=[8, 16], n_groups=4, epochs=7, save_at=[3])
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert TrainConfig.of(**cfg.options()) == cfg
    assert cfg.policy.horizon == 16 and cfg.sobolev.alpha == 0.5 and cfg.optim.lr == 3e-4 and cfg.data.epochs == 7
    old = {"method": "sdp", "T_h": 16, "K": 10, "alpha_sobolev": 0.5, "n_proj": 2, "lr": 3e-4, "down_dims": [8, 16],
           "n_groups": 4, "epochs": 7, "save_at": [3], "betas": [0.95, 0.999], "T_o": 1}   # format_version 1
    assert TrainConfig.from_dict(old) == cfg
    assert flat_options(old)["horizon"] == 16 and set(RENAMED.values()) <= set(options())
    with pytest.raises(SdpError, match=r"unknown training option\(s\) \['T_h'\] \(T_h is now horizon\)"):
        TrainConfig.of(T_h=8)


def test_a_loop_folder_of_the_flat_layout_resumes_with_the_same_settings_only(tmp_path):
    """loop_config.json written before the sections (flat, training options in `train_options` with older names)
    is migrated before the comparison: the same settings resume, another one is refused by its dotted name."""
    from sdp_cli import RESULTS_VERSION
    from sdp_cli.algorithm.loop import LoopConfig, LoopRolloutConfig, check_resume

    train = TrainConfig.of(method="sdp", epochs=5, horizon=8, seed=2, save_at=[2], down_dims=[8, 16], n_groups=4,
                           sobolev_alpha=0.001)
    cfg = LoopConfig(task="pendulum", train=train, rollout=LoopRolloutConfig(t_a=4, n_test=3), n_traj=(2,))
    flat = {"task": "pendulum", "method": "sdp", "n_algo": 1, "n_traj": [2], "epochs": 5, "seed": 2, "horizon": 8,
            "t_a": 4, "eval_t_a": [], "eval_t_a_last": [], "k_rollout": None, "n_test": 3, "test_seed": 0,
            "reset_buffer": True, "max_iter": 1000, "workers": 4, "device": "cpu", "executor": None,
            "scheduler": None, "train_options": {"down_dims": [8, 16], "n_groups": 4, "alpha_sobolev": 0.001},
            "single_shooting": False, "eval_refine": True, "save_at": [2], "to": "ms", "code_rev": "0" * 40,
            "results_version": RESULTS_VERSION}
    out = tmp_path / "run"
    out.mkdir()
    (out / "loop_config.json").write_text(json.dumps(flat))
    check_resume(cfg, out, same_results=True)                  # the same run: resumes
    assert LoopConfig.from_dict(flat, workers=None) == cfg
    (out / "loop_config.json").write_text(json.dumps({**flat, "train_options": {**flat["train_options"],
                                                                                  "alpha_sobolev": 1.0}}))
    with pytest.raises(SdpError, match=r"train\.sobolev\.alpha=1\.0 \(now 0\.001\)"):
        check_resume(cfg, out)


def test_a_loop_rollout_option_added_once_is_a_flag_an_experiment_key_and_a_validated_value(tmp_path):
    """A field added to LoopRolloutConfig (here in a subclass) needs nothing else: `sdp loop`'s flag, the
    experiment key with its type and default, the config a group builds, and its range rule, all from the field."""
    from dataclasses import dataclass

    from typer.testing import CliRunner

    from sdp_cli.cli_options import with_loop_rollout_options
    from sdp_cli.experiments.experiment import GROUP_DEFAULTS, GROUP_TYPES, type_ok
    from sdp_cli.algorithm.loop_options import LoopRolloutConfig, from_group, group_keys, loop_opt

    @dataclass(frozen=True)
    class WithBudget(LoopRolloutConfig):
        eval_budget: int = loop_opt(3, "Evaluations per iteration.", ge=1)
        eval_every: tuple[int, ...] = loop_opt(help="Iterations to evaluate.", factory=tuple, ge=1)

    keys = group_keys(WithBudget)
    assert keys["eval_budget"] == ("int", 3) and keys["eval_every"] == ("[int]", [])
    assert {k: v for k, v in keys.items() if k in GROUP_TYPES} == {k: (GROUP_TYPES[k], GROUP_DEFAULTS[k])
                                                                   for k in group_keys(LoopRolloutConfig)}
    assert not type_ok("3", keys["eval_budget"][0]) and type_ok([1, 2], keys["eval_every"][0])
    cfg = from_group({**{k: d for k, (_, d) in keys.items()}, "eval_budget": 7, "eval_every": [1, 3]}, WithBudget)
    assert cfg.eval_budget == 7 and cfg.eval_every == (1, 3)
    with pytest.raises(SdpError, match="eval_budget"):
        WithBudget(eval_budget=0)

    seen = {}
    app_ = typer.Typer()

    @app_.command()
    @with_loop_rollout_options(WithBudget)
    def run(name: str = "x", rollout=None) -> None:
        seen["rollout"] = rollout

    runner = CliRunner()
    r = runner.invoke(app_, ["--eval-budget", "5", "--eval-every", "2,4", "--no-eval-refine"])
    assert r.exit_code == 0, r.output
    assert (seen["rollout"].eval_budget, seen["rollout"].eval_every, seen["rollout"].eval_refine) == (5, (2, 4), False)
    r = runner.invoke(app_, ["--eval-budget", "0"])
    assert r.exit_code == 1 and "eval_budget" in r.output


def test_every_loop_option_is_a_flag_of_loop_and_an_experiment_key():
    """eval_refine was a flag of `sdp loop` that no experiment file could set, and reset_buffer too: now flag and
    key come from one field (LoopRolloutConfig's, LoopAlgorithmOptions' that LoopConfig inherits)."""
    from dataclasses import fields

    from sdp_cli.experiments.experiment import GROUP_TYPES
    from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, LoopRolloutConfig

    for cls in (LoopRolloutConfig, LoopAlgorithmOptions):
        names = {f.name for f in fields(cls)}
        assert names <= set(_params("loop")) and names <= set(GROUP_TYPES)
    assert {"eval_refine", "reset_buffer", "n_algo", "max_iter", "to"} <= set(GROUP_TYPES)


def test_an_algorithm_option_added_once_is_a_flag_a_key_a_validated_loop_setting_and_a_column(tmp_path):
    """A field added to LoopAlgorithmOptions (here a subclass, with a LoopConfig that inherits it) is at once a
    flag of `sdp loop`, an experiment key with its type and default, a field of the LoopConfig a group builds,
    range-checked, and, where runs differ in it, a column of the report's all_runs.csv (loop_config.json)."""
    from dataclasses import dataclass

    from typer.testing import CliRunner

    from sdp_cli.cli_options import with_loop_algorithm_options
    from sdp_cli.algorithm.loop import LoopConfig
    from sdp_cli.algorithm.loop_options import LoopAlgorithmOptions, from_group, group_keys, loop_opt
    from sdp_cli.policy.config import TrainConfig

    @dataclass(frozen=True, kw_only=True)
    class WithWarmup(LoopAlgorithmOptions):
        warm_iterations: int = loop_opt(0, "Iterations collected from the naive guess only.", ge=0)

    @dataclass(frozen=True)
    class Loop(LoopConfig, WithWarmup):
        pass

    keys = group_keys(WithWarmup)
    assert keys["warm_iterations"] == ("int", 0) and keys["reset_buffer"] == ("bool", True)
    g = {**{k: d for k, (_, d) in keys.items()}, "warm_iterations": 2, "reset_buffer": False}
    cfg = Loop(task="pendulum", train=TrainConfig.of(method="dp"), **from_group(g, WithWarmup))
    assert cfg.warm_iterations == 2 and not cfg.reset_buffer and cfg.to_dict()["warm_iterations"] == 2
    with pytest.raises(SdpError, match="warm_iterations"):
        Loop(task="pendulum", train=TrainConfig.of(method="dp"), warm_iterations=-1)
    with pytest.raises(SdpError, match="to must be one of"):
        Loop(task="pendulum", train=TrainConfig.of(method="dp"), to="cem")

    seen = {}
    app_ = typer.Typer()

    @app_.command()
    @with_loop_algorithm_options(WithWarmup)
    def run(name: str = "x", algorithm=None) -> None:
        seen.update(algorithm)

    runner = CliRunner()
    r = runner.invoke(app_, ["--warm-iterations", "3", "--keep-buffer", "--n-algo", "4"])
    assert r.exit_code == 0, r.output
    assert seen == {"warm_iterations": 3, "reset_buffer": False, "n_algo": 4}

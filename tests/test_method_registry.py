"""Adding a method is one policy class and one registration (sdp_cli.policy.registry): a toy family
(a linear policy, the MLP family's data and loss) trains, checkpoints, loads and rolls out through sdp's
own CLI, and every built-in method is found through the same registry."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.policy import get_method, load_policy, method_names, register_method
from sdp_cli.policy.diffusion import DiffusionUnetPolicy
from sdp_cli.policy.mlp import MLPPolicy
from sdp_cli.policy.registry import _REGISTRY
from synthetic_dataset import write_dataset

runner = CliRunner()


class LinearPolicy(MLPPolicy):
    """``u_n (B, nu) = W [obs_n, xi_n] + b``: the MLP family's samples, loss and ``act``, a linear network."""

    def build_network(self):
        self.lin = nn.Linear(self.dims["n_obs"] + self.dims["n_xi"], self.dims["n_action"])

    def forward(self, obs_n, xi_n):
        return self.lin(torch.cat([obs_n, xi_n], dim=-1))


@pytest.fixture()
def toy_method():
    register_method("toy_linear", LinearPolicy, sobolev=True, description="linear feedback, Sobolev loss")
    yield "toy_linear"
    _REGISTRY.pop("toy_linear", None)


def test_builtin_methods_come_from_the_registry():
    assert set(method_names()) >= {"sdp", "dp", "pddp", "pddp_s"}
    assert get_method("sdp").policy_class is DiffusionUnetPolicy and get_method("sdp").sobolev
    assert get_method("dp").policy_class is DiffusionUnetPolicy and not get_method("dp").sobolev
    assert get_method("pddp_s").policy_class is MLPPolicy and get_method("pddp_s").sobolev
    assert get_method("sdp").chunked and not get_method("pddp").chunked
    assert "toy_linear" not in method_names()


def test_a_registered_toy_method_trains_loads_and_rolls_out(toy_method, tmp_path):
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    r = runner.invoke(app, ["train", "--data", str(data), "--method", toy_method, "--epochs", "2", "--batch-size", "16",
                            "--device", "cpu", "--no-progress", "--out", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    pol = load_policy(tmp_path / "run")
    assert pol.method == toy_method and isinstance(pol, LinearPolicy) and not pol.chunked
    assert set(pol.state_dict()) == {"lin.weight", "lin.bias"} | {k for k in pol.state_dict() if k.startswith("normalizer.")}
    x = np.stack([pol.task.initial_state(pol.task.sample_xi(np.random.default_rng(i))) for i in range(3)])
    xi = np.stack([pol.task.sample_xi(np.random.default_rng(i)) for i in range(3)])
    assert pol.act(x, xi).shape == (3, pol.task.nu)
    r = runner.invoke(app, ["rollout", "--policy", str(tmp_path / "run"), "--n", "2", "--seed", "0",
                            "--out", str(tmp_path / "r.npz")])
    assert r.exit_code == 0, r.output
    arrays, meta = load_npz(tmp_path / "r.npz", kind="rollout")
    assert meta["method"] == toy_method and np.isfinite(arrays["cost"]).all()


def test_unknown_method_is_one_line_listing_the_registered_ones(tmp_path):
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    r = runner.invoke(app, ["train", "--data", str(data), "--method", "nope", "--epochs", "1",
                            "--out", str(tmp_path / "run")])
    assert r.exit_code == 1 and "method must be one of sdp, dp, pddp, pddp_s" in r.output


class _EntryPoint:
    def __init__(self, name, fn):
        self.name, self.value, self._fn = name, f"tests:{name}", fn

    def load(self):
        return self._fn


def test_installed_packages_add_methods_through_the_sdp_methods_entry_point(monkeypatch, capsys):
    """An entry point of the group sdp.methods names a function that registers methods: it is called when the
    registry loads; it cannot replace a built-in method, and one that fails is one line on stderr with the
    registry left as it was."""
    import sdp_cli.policy.registry as reg

    def good():
        register_method("toy_plugin", LinearPolicy, sobolev=False, description="from a package")

    def clash():
        register_method("sdp", LinearPolicy, sobolev=False)

    def broken():
        register_method("toy_half", LinearPolicy, sobolev=False)
        raise RuntimeError("no torch here")

    eps = [_EntryPoint("good", good), _EntryPoint("clash", clash), _EntryPoint("broken", broken)]
    monkeypatch.setattr(reg.importlib.metadata, "entry_points",
                        lambda group: eps if group == reg.ENTRY_POINT_GROUP else [])
    builtin_sdp = get_method("sdp")
    try:
        reg._load_entry_points()
        assert get_method("toy_plugin").policy is LinearPolicy
        assert get_method("sdp") is builtin_sdp and "toy_half" not in method_names()
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 2 and "a built-in method has that name" in err[0] and "no torch here" in err[1]
    finally:
        _REGISTRY.pop("toy_plugin", None)


def test_a_plugin_file_registers_a_method_under_plugin_and_its_old_name(tmp_path, monkeypatch):
    """`sdp --plugin FILE.py` (alias `--task-module`) imports a file that may register methods too."""
    import sys

    import sdp_cli.tasks as tasks_module

    monkeypatch.delenv(tasks_module.TASK_MODULES_ENV, raising=False)      # (restored after the test)
    monkeypatch.setattr(tasks_module, "_LOADED_FILES", set())
    before = set(sys.modules)
    f = tmp_path / "more_methods.py"
    f.write_text("from sdp_cli.policy.registry import register_method\n"
                 "register_method('toy_file', 'sdp_cli.policy.mlp:MLPPolicy', sobolev=False, chunked=False,\n"
                 "                description='an MLP under another name')\n")
    try:
        for flag in ("--plugin", "--task-module"):
            _REGISTRY.pop("toy_file", None)
            tasks_module._LOADED_FILES.clear()
            r = runner.invoke(app, [flag, str(f), "train", "--help"])
            assert r.exit_code == 0, r.output
            assert "toy_file" in method_names()
    finally:
        _REGISTRY.pop("toy_file", None)
        for m in set(sys.modules) - before:
            if m.startswith("sdp_task_module_"):
                sys.modules.pop(m)


def test_stacking_is_a_capability_a_family_opts_into():
    """The runner stacks runs only of a family that says it can (the diffusion U-Net); a chunked family that
    does not (here the diffusion family with the capability switched off, as a plugin of another kind would
    be) trains each run alone instead of failing in the stacker."""
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.train_stack import stackable

    class SoloChunks(DiffusionUnetPolicy):
        stackable = False

    register_method("toy_solo_chunks", SoloChunks, sobolev=False)
    try:
        assert stackable(TrainConfig.of(method="dp")) and stackable(TrainConfig.of(method="sdp"))
        assert not stackable(TrainConfig.of(method="toy_solo_chunks"))
        assert not stackable(TrainConfig.of(method="pddp"))
    finally:
        _REGISTRY.pop("toy_solo_chunks", None)

"""Adding a method is one family class and one registration (sdp_cli.policy.registry): a toy method
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
from sdp_cli.data.normalizer import Normalizer
from sdp_cli.policy import get_method, load_policy, method_names, register_method
from sdp_cli.policy.families import DiffusionFamily, MLPFamily
from sdp_cli.policy.registry import _REGISTRY
from synthetic_dataset import write_dataset

runner = CliRunner()


class LinearNet(nn.Module):
    """``u_n (B, nu) = W [obs_n, xi_n] + b``, with the normalizer every policy network carries."""

    def __init__(self, dims: dict):
        super().__init__()
        self.normalizer = Normalizer(dims["n_action"], dims["n_obs"] + dims["n_action"], dims["n_xi"], dims["ndx"])
        self.lin = nn.Linear(dims["n_obs"] + dims["n_xi"], dims["n_action"])

    def forward(self, obs_n, xi_n):
        return self.lin(torch.cat([obs_n, xi_n], dim=-1))


class LinearFamily(MLPFamily):
    """The MLP family's samples, loss and runtime policy, with a linear network."""

    def build_net(self, cfg, dims):
        return LinearNet(dims)


@pytest.fixture()
def toy_method():
    register_method("toy_linear", LinearFamily(), sobolev=True, description="linear feedback, Sobolev loss")
    yield "toy_linear"
    _REGISTRY.pop("toy_linear", None)


def test_builtin_methods_come_from_the_registry():
    assert set(method_names()) >= {"sdp", "dp", "pddp", "pddp_s"}
    assert isinstance(get_method("sdp").family, DiffusionFamily) and get_method("sdp").sobolev
    assert isinstance(get_method("dp").family, DiffusionFamily) and not get_method("dp").sobolev
    assert isinstance(get_method("pddp_s").family, MLPFamily) and get_method("pddp_s").sobolev
    assert "toy_linear" not in method_names()


def test_a_registered_toy_method_trains_loads_and_rolls_out(toy_method, tmp_path):
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    r = runner.invoke(app, ["train", "--data", str(data), "--method", toy_method, "--epochs", "2", "--batch-size", "16",
                            "--device", "cpu", "--no-progress", "--out", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    pol = load_policy(tmp_path / "run")
    assert pol.method == toy_method and isinstance(pol.net, LinearNet) and not pol.is_diffusion
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

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
    from sdp_cli.training.train_stack import stackable

    class SoloChunks(DiffusionUnetPolicy):
        stackable = False

    register_method("toy_solo_chunks", SoloChunks, sobolev=False)
    try:
        assert stackable(TrainConfig.of(method="dp")) and stackable(TrainConfig.of(method="sdp"))
        assert not stackable(TrainConfig.of(method="toy_solo_chunks"))
        assert not stackable(TrainConfig.of(method="pddp"))
    finally:
        _REGISTRY.pop("toy_solo_chunks", None)


CHUNK_MLP = '''
"""A chunked family that is no diffusion policy: a chunk of T_h actions from (xi, o_hist) by an MLP."""
import numpy as np
import torch
from torch import nn

from sdp_cli.data.normalizer import Normalizer
from sdp_cli.policy.base import Policy, as_tensor
from sdp_cli.policy.diffusion import DiffusionUnetPolicy
from sdp_cli.policy.registry import register_method


class ChunkMLPPolicy(Policy):
    chunked = True
    make_dataset = DiffusionUnetPolicy.make_dataset      # the chunk samples (B, T_h, A) of the diffusion family
    dims_for = DiffusionUnetPolicy.dims_for
    a_hist = DiffusionUnetPolicy.a_hist

    def __init__(self, config, dims):
        super().__init__(config, dims)
        d, p = self.dims, config.policy
        self.normalizer = Normalizer(d["n_action"], d["n_obs"], d["n_xi"], d["ndx"])
        self.net = nn.Sequential(nn.Linear(d["n_xi"] + p.n_obs_steps * d["n_obs"], 32), nn.Mish(),
                                 nn.Linear(32, p.horizon * d["n_action"]))

    T_h = property(lambda self: self.config.policy.horizon)
    T_o = property(lambda self: self.config.policy.n_obs_steps)

    def _chunk(self, xi_n, obs_n):
        return self.net(torch.cat([xi_n, obs_n.flatten(1)], -1)).reshape(len(xi_n), self.T_h, -1)

    def balance_terms(self, t):
        return t["tau0"][:, self.T_o:], t["jac"][:, self.T_o:]

    def compute_loss(self, batch, generator=None):
        dp = ((self._chunk(batch["xi"], batch["obs"])[:, self.T_o:] - batch["tau0"][:, self.T_o:]) ** 2).mean()
        return dp, {"dp": dp.detach(), "sobolev": torch.zeros(())}

    @torch.no_grad()
    def predict_chunk(self, xi, x_hist, u_hist, generator=None):
        x_hist, u_hist = np.asarray(x_hist, float), np.asarray(u_hist, float)
        x_hist = x_hist[:, None] if x_hist.ndim == 2 else x_hist
        u_hist = u_hist[:, None] if u_hist.ndim == 2 else u_hist
        tau = self._chunk(self.normalizer.normalize("xi", as_tensor(xi, self.device)), self._obs(x_hist, u_hist))
        tau[:, :self.T_o] = self.normalizer.normalize("action", as_tensor(self.a_hist(x_hist, u_hist), self.device))
        return self.normalizer.unnormalize("action", tau).double().cpu().numpy()


register_method("chunk_mlp", ChunkMLPPolicy, sobolev=False, description="chunk MLP (test plugin)")
'''

EXPERIMENT = """description: a chunked family that is no diffusion policy, through the pipeline
groups:
  g:
    task: pendulum
    methods: [chunk_mlp, dp]
    seeds: [0, 1]
    n_traj: [2]
    n_algo: 1
    epochs: 2
    horizon: 12
    t_a: 4
    n_test: 2
    train: {batch_size: 16, down_dims: [8, 16], n_groups: 4, step_embed_dim: 8}
"""


def test_a_chunked_family_that_is_no_diffusion_policy_runs_through_every_command(tmp_path, monkeypatch):
    """A chunk MLP loaded with --plugin (no U-Net, no scheduler, no K): T_h 12 (no U-Net rule), train, rollout,
    loop, `pipeline --run` with stacking on (its runs train alone, the dp runs of the group in a stack),
    `--estimate` (one network call per plan) and report. At 3cd1b8b `pipeline --run` ended in
    AttributeError: 'ChunkMLPPolicy' object has no attribute 'unet'."""
    import pandas as pd

    from sdp_cli.experiments.estimate import estimate

    plugin = tmp_path / "chunk_mlp.py"
    plugin.write_text(CHUNK_MLP)
    monkeypatch.chdir(tmp_path)
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    sdp = lambda *a: runner.invoke(app, ["--plugin", str(plugin), *a])   # noqa: E731
    try:
        r = sdp("train", "--data", str(data), "--method", "chunk_mlp", "--horizon", "12", "--epochs", "2",
                "--batch-size", "16", "--device", "cpu", "--no-progress", "--out", "run")
        assert r.exit_code == 0, r.output
        pol = load_policy(tmp_path / "run")
        assert pol.chunked and pol.max_t_a == 11 and pol.sampler_options() == {} and not hasattr(pol, "unet")
        r = sdp("rollout", "--policy", "run", "--n", "2", "--t-a", "5", "--out", "ro.npz", "--no-progress")
        assert r.exit_code == 0, r.output
        assert load_npz(tmp_path / "ro.npz")[0]["X"].shape[0] == 2
        r = sdp("rollout", "--policy", "run", "--n", "2", "--k-rollout", "2", "--out", "ro2.npz")
        assert r.exit_code == 1 and "has no sampler" in r.output
        r = sdp("loop", "--task", "pendulum", "--method", "chunk_mlp", "--horizon", "12", "--n-traj", "2",
                "--n-algo", "1", "--epochs", "2", "--batch-size", "16", "--n-test", "2", "--t-a", "4", "--out", "loop",
                "--no-progress")
        assert r.exit_code == 0, r.output
        (tmp_path / "pipelines").mkdir()
        (tmp_path / "pipelines" / "chunks.yaml").write_text(EXPERIMENT)
        df, _ = estimate("chunks", workers=2, budget_s=2, root=tmp_path)
        mlp, dp = df[df.run.str.contains("chunk_mlp")], df[df.run.str.contains("-dp-")]
        assert len(mlp) == 2 and len(dp) == 2 and (df.train_cpu_s > 0).all()
        assert set(dp["stack"]) == {2} and set(mlp["stack"]) == {1}          # only the U-Net stacks
        r = sdp("pipeline", "chunks", "--run", "--workers", "1", "--stack", "8")
        assert r.exit_code == 0, r.output
        assert "train 2 runs as one stack" in r.output and "chunk_mlp" in r.output
        r = sdp("report", "--runs", "runs/chunks", "--out", "report")
        assert r.exit_code == 0, r.output
        rows = pd.read_csv(tmp_path / "report" / "all_runs.csv")
        assert set(rows.method) >= {"chunk_mlp", "dp"} and rows.policy_cost_mean.notna().all()
    finally:
        _REGISTRY.pop("chunk_mlp", None)

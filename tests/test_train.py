"""``sdp train``: all methods, checkpoints, metrics, resume after a kill, --init, --save-at, bad input."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.errors import SdpError
from sdp_cli.policy import DiffusionUnetPolicy, MLPPolicy, load_policy
from sdp_cli.policy.checkpoint import load_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train
from synthetic_dataset import write_dataset

T = 30
TINY = dict(horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=32, mlp_hidden=[32, 32],
            checkpoint_every_s=1e9)


def cfg(method, **kw):
    return TrainConfig.of(method=method, **{**TINY, **kw})


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("train")
    return {"ok": write_dataset(d / "p.npz", "pendulum", n_traj=3, seed=0, T=T),
            "nogain": write_dataset(d / "nogain.npz", "pendulum", n_traj=2, seed=1, T=T, drop=("K", "Phi")),
            "double": write_dataset(d / "dp.npz", "double_pendulum", n_traj=2, seed=2, T=T)}


def quiet(*_):
    pass


def rows(run):
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("method", ["sdp", "dp", "pddp", "pddp_s"])
def test_all_methods_train_and_load(data, tmp_path, method):
    run = tmp_path / method
    path = train(data["ok"], run, cfg(method, epochs=3), device="cpu", progress=False, log=quiet)
    ck = load_checkpoint(path)
    assert ck["finished"] and ck["step"] == ck["total_steps"] and ck["task"] == "pendulum"
    assert len(ck["dataset"]["sha256"]) == 64 and ck["provenance"]["versions"]["torch"]
    m = rows(run)
    assert len(m) == ck["total_steps"]
    assert set(m[0]) >= {"step", "loss", "sobolev", "lr"} and "wall_time" not in m[0]   # (in the sidecar)
    sob = [float(r["sobolev"]) for r in m]
    assert (max(sob) > 0) == (method in ("sdp", "pddp_s"))
    pol = load_policy(run)
    B = 4
    xi = np.tile(data_xi(data["ok"]), (B, 1))
    x = xi.copy()
    if method in ("sdp", "dp"):
        assert isinstance(pol, DiffusionUnetPolicy)
        u_prev = np.full((B, 1), 0.5)
        g = lambda: torch.Generator().manual_seed(3)
        tau = pol.predict_chunk(xi, x, u_prev, generator=g())
        assert tau.shape == (B, 8, 1)
        np.testing.assert_allclose(tau[:, 0], u_prev, atol=1e-5)        # inpainted history
        np.testing.assert_allclose(tau, pol.predict_chunk(xi, x, u_prev, generator=g()))  # seeded
        tau2 = pol.predict_chunk(xi, x, u_prev, generator=g(), k_rollout=2)
        assert tau2.shape == tau.shape and np.all(np.isfinite(tau2))
    else:
        assert isinstance(pol, MLPPolicy)
        assert pol.act(x, xi).shape == (B, 1)


def data_xi(path):
    return np.load(path)["xi"][:1]


def test_vjp_mode_and_state_action_train(data, tmp_path):
    train(data["ok"], tmp_path / "a", cfg("sdp", epochs=2, sobolev_mode="vjp"), device="cpu", progress=False,
          log=quiet)
    train(data["ok"], tmp_path / "b", cfg("sdp", epochs=2, action="x"), device="cpu", progress=False, log=quiet)
    pol = load_policy(tmp_path / "b")
    x = np.load(data["ok"])["X"][0, :2]
    tau = pol.predict_chunk(x, x, np.zeros((2, 1)), generator=torch.Generator().manual_seed(0))
    assert tau.shape == (2, 8, 2)
    np.testing.assert_allclose(tau[:, 0], x, atol=1e-5)   # a_hist = g(x_t) = x_t


class Killed(Exception):
    pass


def test_resume_after_kill_is_bit_identical(data, tmp_path):
    c = cfg("sdp", epochs=4, save_at=[2, 3])
    ref = train(data["ok"], tmp_path / "ref", c, device="cpu", progress=False, log=quiet)

    def kill(step):
        if step == 2:
            raise Killed
    c_every = cfg("sdp", epochs=4, save_at=[2, 3], checkpoint_every_s=0.0)
    with pytest.raises(Killed):
        train(data["ok"], tmp_path / "run", c_every, device="cpu", progress=False, log=quiet, on_step=kill)
    assert load_checkpoint(tmp_path / "run")["step"] == 2   # last checkpoint before the kill
    with pytest.raises(SdpError, match="--resume"):
        train(data["ok"], tmp_path / "run", c_every, device="cpu", progress=False, log=quiet)
    got = train(data["ok"], tmp_path / "run", c_every, device="cpu", resume=True, progress=False, log=quiet)
    a, b = load_checkpoint(ref), load_checkpoint(got)
    for key in ("model", "ema_model"):
        for k in a[key]:
            torch.testing.assert_close(a[key][k], b[key][k], atol=0, rtol=0)
    assert [r["step"] for r in rows(tmp_path / "run")] == [str(s) for s in range(1, 5)]
    assert [r["loss"] for r in rows(tmp_path / "run")] == [r["loss"] for r in rows(tmp_path / "ref")]
    assert (tmp_path / "run" / "epoch_2.pt").is_file() and (tmp_path / "run" / "epoch_3.pt").is_file()
    assert load_checkpoint(tmp_path / "run" / "epoch_3.pt")["epoch"] == 3


def _as_format_version_1(path):
    """Rewrite a checkpoint the way sdp wrote it before the config sections: one flat config with the older
    names (T_h, T_o, K, alpha_sobolev, n_proj), format_version 1."""
    raw = torch.load(path, weights_only=True)
    flat = {}
    for k, v in raw["config"].items():
        flat.update(v if isinstance(v, dict) else {k: v})
    for old, new in (("horizon", "T_h"), ("n_obs_steps", "T_o"), ("diffusion_steps", "K")):
        flat[new] = flat.pop(old)
    sob = raw["config"]["sobolev"]
    for name in ("alpha", "balance", "path", "n_proj", "mode", "fraction", "cap"):
        flat.pop(name)
    flat.update({"alpha_sobolev": sob["alpha"], "sobolev_balance": sob["balance"], "sobolev_path": sob["path"],
                 "n_proj": sob["n_proj"], "sobolev_mode": sob["mode"], "sobolev_fraction": sob["fraction"],
                 "sobolev_cap": sob["cap"]})
    torch.save({**raw, "config": flat, "format_version": 1}, path)


def test_a_format_version_1_checkpoint_loads_and_resumes_bit_for_bit(data, tmp_path):
    """Runs in progress when the config got its sections resume: the version-1 checkpoint is migrated on reading
    and the resumed run equals an uninterrupted one."""
    c = cfg("sdp", epochs=4, checkpoint_every_s=0.0)
    ref = train(data["ok"], tmp_path / "ref", c, device="cpu", progress=False, log=quiet)

    def kill(step):
        if step == 2:
            raise Killed
    with pytest.raises(Killed):
        train(data["ok"], tmp_path / "run", c, device="cpu", progress=False, log=quiet, on_step=kill)
    _as_format_version_1(tmp_path / "run" / "checkpoint.pt")
    old = load_checkpoint(tmp_path / "run")
    assert old["format_version"] == 2   # migrated when read (alpha: the task's default, resolved by train)
    assert TrainConfig.from_dict(old["config"]) == c.with_options(sobolev_alpha=1.0)
    assert load_policy(tmp_path / "run").T_h == 8
    got = train(data["ok"], tmp_path / "run", c, device="cpu", resume=True, progress=False, log=quiet)
    a, b = load_checkpoint(ref), load_checkpoint(got)
    for k in a["model"]:
        torch.testing.assert_close(a["model"][k], b["model"][k], atol=0, rtol=0)
    assert [r["loss"] for r in rows(tmp_path / "run")] == [r["loss"] for r in rows(tmp_path / "ref")]
    assert torch.load(got, weights_only=True)["format_version"] == 2


def test_init_keeps_weights_and_widens_the_normalizer(data, tmp_path):
    first = train(data["ok"], tmp_path / "first", cfg("pddp_s", epochs=2), device="cpu", progress=False, log=quiet)
    # a second dataset with 3x larger torques: --init must widen the normalizer to cover it
    other = write_dataset(tmp_path / "other.npz", "pendulum", n_traj=2, seed=7, T=T, u_scale=3.0)
    second = train(other, tmp_path / "second", cfg("pddp_s", epochs=1, mlp_hidden=[64]), device="cpu",
                   init=first, progress=False, log=quiet)
    a, b = load_checkpoint(first), load_checkpoint(second)
    lo = lambda ck, kind: ck["model"][f"normalizer.{kind}_center"] - ck["model"][f"normalizer.{kind}_scale"]
    hi = lambda ck, kind: ck["model"][f"normalizer.{kind}_center"] + ck["model"][f"normalizer.{kind}_scale"]
    U = np.load(other)["U"]
    assert U.max() > float(hi(a, "action").max()) + 1e-3         # outside the first policy's range
    for kind in ("action", "obs", "xi"):                           # the union of both ranges
        assert torch.all(lo(b, kind) <= lo(a, kind) + 1e-6) and torch.all(hi(b, kind) >= hi(a, kind) - 1e-6)
    assert float(lo(b, "action").min()) <= U.min() + 1e-4 and float(hi(b, "action").max()) >= U.max() - 1e-4
    assert b["config"]["policy"]["mlp_hidden"] == [32, 32]    # architecture of the init checkpoint wins
    # recorded relative to the checkpoint folder
    assert (tmp_path / "second" / b["init"]).resolve() == Path(first).resolve()


def test_init_diffusion_policy_can_output_the_new_range(data, tmp_path):
    """With clip_sample the diffusion policy's outputs lie in its normalizer's range: after --init on
    wider data, a prediction pushed to the clip bound reaches the new data's largest torque."""
    first = train(data["ok"], tmp_path / "first", cfg("dp", epochs=1), device="cpu", progress=False, log=quiet)
    other = write_dataset(tmp_path / "other.npz", "pendulum", n_traj=2, seed=7, T=T, u_scale=3.0)
    train(other, tmp_path / "second", cfg("dp", epochs=1), device="cpu", init=first, progress=False, log=quiet)
    U = np.load(other)["U"]
    for run, ok in ((tmp_path / "first", False), (tmp_path / "second", True)):
        pol = load_policy(run)
        top = float(pol.norm.unnormalize("action", torch.ones(1))[0])   # the largest clipped output
        assert (top >= U.max() - 1e-4) == ok


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_train_and_bad_input(data, tmp_path):
    r = invoke("train", "--data", data["nogain"], "--method", "sdp", "--epochs", 1, "--out", tmp_path / "x",
               "--no-progress")
    assert r.exit_code == 1 and "no feedback gains" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1
    r = invoke("train", "--data", data["nogain"], "--method", "pddp_s", "--epochs", 1, "--out", tmp_path / "y",
               "--no-progress")
    assert r.exit_code == 1 and "no feedback gains" in r.output
    r = invoke("train", "--data", data["nogain"], "--method", "dp", "--epochs", 1, "--out", tmp_path / "dp",
               "--horizon", 8, "--batch-size", 16, "--no-progress")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "dp" / "checkpoint.pt").is_file() and (tmp_path / "dp" / "metrics.csv").is_file()
    # --init from a pendulum policy on a double-pendulum dataset: mismatched task
    r = invoke("train", "--data", data["double"], "--method", "dp", "--epochs", 1, "--out", tmp_path / "z",
               "--init", tmp_path / "dp", "--no-progress")
    assert r.exit_code == 1 and "does not match" in r.output and len(r.output.strip().splitlines()) == 1
    r = invoke("train", "--data", data["ok"], "--method", "foo", "--epochs", 1, "--out", tmp_path / "w")
    assert r.exit_code == 1 and "method must be one of" in r.output
    r = invoke("train", "--data", tmp_path / "missing.npz", "--method", "dp", "--epochs", 1, "--out", tmp_path / "v")
    assert r.exit_code == 1 and "not found" in r.output
    r = invoke("train", "--data", data["ok"], "--method", "dp", "--epochs", 1, "--out", tmp_path / "u",
               "--horizon", 12)
    assert r.exit_code == 1 and "divisible" in r.output


def test_sobolev_cap_only_lowers_the_sobolev_term(data, tmp_path):
    """Same seed, same batches and projections: capped weights (<= 1) can only lower the Sobolev
    term of each step, and leave the DDPM term of the first step unchanged."""
    train(data["double"], tmp_path / "plain", cfg("sdp", epochs=1), device="cpu", progress=False, log=quiet)
    path = train(data["double"], tmp_path / "cap", cfg("sdp", epochs=1, sobolev_cap=0.5), device="cpu",
                 progress=False, log=quiet)
    assert load_checkpoint(path)["config"]["sobolev"]["cap"] == 0.5
    a, b = rows(tmp_path / "plain")[0], rows(tmp_path / "cap")[0]
    assert float(b["dp"]) == pytest.approx(float(a["dp"]), rel=1e-6)
    assert 0 < float(b["sobolev"]) < float(a["sobolev"])


def test_epoch_sampling_without_replacement():
    from sdp_cli.data.sampling import batch_indices, epoch_indices, steps_per_epoch

    n, E, B = 100, 53, 16
    assert steps_per_epoch(E, B) == 4
    for epoch in range(3):
        idx = epoch_indices(n, E, seed=7, epoch=epoch)
        assert len(idx) == E and len(set(idx.tolist())) == E and 0 <= int(idx.min()) and int(idx.max()) < n
        batches = [batch_indices(n, E, B, 7, epoch * 4 + j) for j in range(4)]
        assert [len(b) for b in batches] == [16, 16, 16, 5]
        assert torch.equal(torch.cat(batches), idx)
    assert not torch.equal(epoch_indices(n, E, 7, 0), epoch_indices(n, E, 7, 1))
    assert torch.equal(epoch_indices(n, E, 7, 2), epoch_indices(n, E, 7, 2))
    assert len(epoch_indices(10, 10, 0, 0).unique()) == 10       # MLP epochs: every pair once


@pytest.mark.parametrize("method", ["sdp", "pddp"])
def test_train_steps_see_one_epoch_of_distinct_samples(data, tmp_path, monkeypatch, method):
    """Each epoch trains ceil(E / B) steps on E distinct samples, the last batch smaller."""
    import sdp_cli.training.train as tr

    seen = []
    orig = tr.Run.next_batch

    def recording(run):
        batch = orig(run)
        seen.append(next(iter(batch.values())).clone())
        return batch

    monkeypatch.setattr(tr.Run, "next_batch", recording)
    c = cfg(method, epochs=2, batch_size=16)
    path = train(data["ok"], tmp_path / "r", c, device="cpu", progress=False, log=quiet)
    ck = load_checkpoint(path)
    E = int(np.ceil(3 * (T - c.policy.horizon) / c.policy.horizon)) if method == "sdp" else 3 * T
    spe = int(np.ceil(E / 16))
    assert ck["steps_per_epoch"] == spe and ck["total_steps"] == 2 * spe == len(seen)
    sizes = [len(b) for b in seen[:spe]]
    assert sizes == [16] * (spe - 1) + [E - 16 * (spe - 1)]
    first = torch.cat(seen[:spe])
    assert len(first) == E and len(torch.unique(first, dim=0)) == E   # no sample twice in an epoch


def test_metrics_csv_follows_training_between_checkpoints(data, tmp_path, monkeypatch):
    """metrics.csv is appended to while training runs (not only with each checkpoint), row for row."""
    import sdp_cli.data.metrics_log as ml

    monkeypatch.setattr(ml, "METRICS_EVERY_S", 0.0)
    seen = {}

    def look(step):
        seen[step] = [int(r["step"]) for r in rows(tmp_path / "r")]

    train(data["ok"], tmp_path / "r", cfg("dp", epochs=4, batch_size=16), device="cpu", progress=False, log=quiet,
          on_step=look)
    assert seen and all(v == list(range(1, s + 1)) for s, v in seen.items())

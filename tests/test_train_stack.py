"""Many runs at once (sdp_cli.training.train_stack): a run trained in a stack equals the same run trained alone, to float32
rounding, whichever runs share its stack; its checkpoint is a solo one (load_policy, resume); a killed stack
resumes every member."""

from __future__ import annotations

import csv

import pytest
import torch

from sdp_cli.errors import SdpError
from sdp_cli.policy import load_policy
from sdp_cli.policy.checkpoint import load_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train
from sdp_cli.training.train_stack import train_stack
from synthetic_dataset import write_dataset

T = 30
TINY = dict(horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=16, checkpoint_every_s=1e9)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("stack")
    return {n: write_dataset(d / f"p{n}.npz", "pendulum", n_traj=n, seed=n, T=T) for n in (2, 3, 5)}


def quiet(*_):
    pass


def rows(run):
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def _members(method):
    # different datasets (n_traj), seeds, epochs (so one member finishes first), learning rates and the other
    # optimisation settings each member keeps (clipping bound, weight decay, betas, EMA warm-up power);
    # "mixed": one network shape, three losses (SDP with 2 projections on half its batch, DP, SDP by default)
    m = ["sdp", "dp", "sdp"] if method == "mixed" else [method] * 3
    extra = dict(sobolev_n_proj=2, sobolev_fraction=0.5) if method == "mixed" else {}
    return [(2, TrainConfig.of(method=m[0], seed=0, epochs=6, lr=1e-3, **extra, **TINY)),
            (5, TrainConfig.of(method=m[1], seed=1, epochs=4, lr=3e-3, save_at=[2], grad_clip=0.05,
                               weight_decay=1e-2, betas=[0.9, 0.99], ema_power=0.5, **TINY)),
            (3, TrainConfig.of(method=m[2], seed=2, epochs=5, lr=1e-3, sobolev_alpha=0.5, **TINY))]


def _close(a, b, tol, lr=None):
    """Weights equal to float32 rounding: within ``tol`` each, or, with ``lr`` (after AdamW steps, which divide a
    gradient by its running RMS, so a gradient element that is zero but for rounding moves its weight by up to lr
    in either run), 99% of the elements within ``tol`` and all within lr / 20."""
    for key in ("model", "ema_model"):
        diffs = torch.cat([(a[key][k] - b[key][k]).abs().flatten() for k in a[key]])
        if lr is None:
            assert diffs.max() <= tol, key
        else:
            assert (diffs <= tol).float().mean() >= 0.99 and diffs.max() <= lr / 20, (key, diffs.max())


@pytest.fixture
def float64():
    """Networks in float64, where the grouped kernels' other summation order is invisible: a stacked run must then
    equal its solo run to 1e-10 (in float32, AdamW's division by the gradient's RMS turns the rounding of a
    near-zero gradient element into weight differences of up to a fraction of lr: checked separately)."""
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(torch.float32)


@pytest.mark.parametrize("method", ["sdp", "dp", "mixed"])
def test_a_stacked_run_equals_the_same_run_trained_alone(data, tmp_path, method, float64):
    members = _members(method)
    solo = [train(data[n], tmp_path / f"solo{i}", c, device="cpu", progress=False, log=quiet)
            for i, (n, c) in enumerate(members)]
    got = train_stack([data[n] for n, _ in members], [tmp_path / f"st{i}" for i in range(3)],
                      [c for _, c in members], log=quiet)
    for i, (a, b) in enumerate(zip(solo, got)):
        A, Bk = load_checkpoint(a), load_checkpoint(b)
        assert Bk["finished"] and Bk["step"] == A["step"] and Bk["config"] == A["config"]
        assert A["model"]["unet.final.1.weight"].dtype == torch.float64
        _close(A, Bk, 1e-10)
        ra, rb = rows(tmp_path / f"solo{i}"), rows(tmp_path / f"st{i}")
        assert [r["step"] for r in ra] == [r["step"] for r in rb]
        for x, y in zip(ra, rb):
            assert float(y["loss"]) == pytest.approx(float(x["loss"]), rel=1e-5)
    assert (tmp_path / "st1" / "epoch_2.pt").is_file()
    pol = load_policy(tmp_path / "st2")                      # a member's checkpoint is a solo one
    assert pol.method == members[2][1].method and pol.T_h == 8
    # the same run in another stack (another companion, fewer members): the same result
    other = train_stack([data[3], data[2]], [tmp_path / "o2", tmp_path / "o0"], [members[2][1], members[0][1]],
                        log=quiet)
    _close(load_checkpoint(got[2]), load_checkpoint(other[0]), 1e-10)


def test_in_float32_a_stacked_run_stays_within_rounding_of_its_solo_run(data, tmp_path):
    members = _members("sdp")
    for i, (n, c) in enumerate(members):
        solo = train(data[n], tmp_path / f"solo{i}", c, device="cpu", progress=False, log=quiet)
        members[i] = (n, c, solo)
    got = train_stack([data[n] for n, _, _ in members], [tmp_path / f"st{i}" for i in range(3)],
                      [c for _, c, _ in members], log=quiet)
    for (n, c, solo), b in zip(members, got):
        _close(load_checkpoint(solo), load_checkpoint(b), 1e-6, lr=c.optim.lr)


def test_a_killed_stack_resumes_every_member(data, tmp_path):
    members = _members("sdp")
    outs = [tmp_path / f"st{i}" for i in range(3)]
    ref = train_stack([data[n] for n, _ in members], [tmp_path / f"ref{i}" for i in range(3)],
                      [c for _, c in members], log=quiet)

    class Killed(Exception):
        pass

    def kill(step):
        if step == 3:
            raise Killed

    every = [c.with_options(checkpoint_every_s=0.0) for _, c in members]
    with pytest.raises(Killed):
        train_stack([data[n] for n, _ in members], outs, every, log=quiet, on_step=kill)
    assert all(load_checkpoint(o)["step"] == 3 for o in outs)
    got = train_stack([data[n] for n, _ in members], outs, every, log=quiet)
    for a, b in zip(ref, got):
        _close(load_checkpoint(a), load_checkpoint(b), 1e-6)


def test_incompatible_runs_are_refused(data, tmp_path):
    a = TrainConfig.of(method="sdp", **TINY)
    for other in (a.with_options(horizon=16), a.with_options(batch_size=8), a.with_options(down_dims=[8, 8])):
        with pytest.raises(SdpError, match="cannot share a stack"):   # another network shape or batch
            train_stack([data[2], data[3]], [tmp_path / "a", tmp_path / "b"], [a, other], log=quiet)
    with pytest.raises(SdpError, match="not stackable"):
        train_stack([data[2]], [tmp_path / "c"], [a.with_options(sobolev_mode="vjp")], log=quiet)


def test_a_member_that_diverges_leaves_the_stack_and_the_others_train_on(data, tmp_path, float64):
    """With ``failed`` (as `sdp pipeline --run` trains its stacks), a member whose loss diverges leaves the stack
    (its fresh folder removed, the reason recorded) and the others finish as they would have without it."""
    members = _members("dp")
    cfgs = [c for _, c in members]
    cfgs[1] = cfgs[1].with_options(lr=1e30)          # diverges at once
    outs = [tmp_path / f"st{i}" for i in range(3)]
    failed = {}
    got = train_stack([data[n] for n, _ in members], outs, cfgs, log=quiet, failed=failed)
    assert list(failed) == [outs[1]] and "diverged" in failed[outs[1]] and not outs[1].exists()
    assert got == [outs[0] / "checkpoint.pt", outs[2] / "checkpoint.pt"]
    ref = train_stack([data[members[0][0]], data[members[2][0]]], [tmp_path / "r0", tmp_path / "r2"],
                      [cfgs[0], cfgs[2]], log=quiet)
    for a, b in zip(got, ref):
        assert load_checkpoint(a)["finished"]
        _close(load_checkpoint(a), load_checkpoint(b), 1e-10)
    with pytest.raises(SdpError, match="diverged"):   # without ``failed``: the stack stops
        train_stack([data[2], data[3]], [tmp_path / "x0", tmp_path / "x1"], [cfgs[0], cfgs[1]], log=quiet)

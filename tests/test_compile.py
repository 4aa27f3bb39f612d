"""TrainConfig.compile (`sdp train --compile`): the U-Net's forward and tangent pass through torch.compile for
training. Fast: who may compile, and that a compiled run is another run (stack key, resume). Slow (-m slow, minutes
of inductor compile): a compiled solo run and a compiled stack train to the eager run's losses at float32 rounding,
their checkpoints record it and load as eager policies."""

from __future__ import annotations

import csv

import pytest
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.errors import SdpError
from sdp_cli.policy.checkpoint import load_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train
from sdp_cli.training.train_stack import stack_key, train_stack
from synthetic_dataset import write_dataset

TINY = dict(horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=16, checkpoint_every_s=1e9)


def quiet(*_):
    pass


def test_only_a_family_that_compiles_may_and_a_compiled_run_is_another_run(tmp_path):
    with pytest.raises(SdpError, match="does not compile its network"):
        TrainConfig.of(method="pddp", compile=True)
    c = TrainConfig.of(method="sdp", compile=True, **TINY)
    assert c.to_dict()["compile"] is True and TrainConfig.from_dict(c.to_dict()).compile
    assert stack_key("pendulum", c) != stack_key("pendulum", c.with_options(compile=False))
    data = write_dataset(tmp_path / "d.npz", "pendulum", n_traj=2, T=30)
    r = CliRunner().invoke(app, ["train", "--data", str(data), "--method", "pddp", "--compile", "--out",
                                 str(tmp_path / "r")])
    assert r.exit_code == 1 and "does not compile its network" in r.output and "Traceback" not in r.output
    eager = TrainConfig.of(method="dp", epochs=1, **TINY)
    train(data, tmp_path / "e", eager, device="cpu", progress=False, log=quiet)
    with pytest.raises(SdpError, match="compile"):     # resuming an eager run compiled changes its numbers
        train(data, tmp_path / "e", eager.with_options(epochs=2, compile=True), device="cpu", resume=True,
              progress=False, log=quiet)


def _losses(run):
    with open(run / "metrics.csv", newline="") as f:
        return [float(r["loss"]) for r in csv.DictReader(f)]


@pytest.mark.slow
def test_compiled_training_equals_eager_training_to_rounding(tmp_path):
    data = {n: write_dataset(tmp_path / f"d{n}.npz", "pendulum", n_traj=n, seed=n, T=30) for n in (2, 3)}
    cfg = TrainConfig.of(method="sdp", epochs=3, seed=1, **TINY)
    runs = {}
    for on in (False, True):
        c = cfg.with_options(compile=on)
        runs[("solo", on)] = [train(data[2], tmp_path / f"solo{on}", c, device="cpu", progress=False, log=quiet)]
        runs[("stack", on)] = train_stack([data[2], data[3]], [tmp_path / f"st{on}a", tmp_path / f"st{on}b"],
                                          [c, c.with_options(seed=2)], log=quiet)
    for kind in ("solo", "stack"):
        for e, c in zip(runs[(kind, False)], runs[(kind, True)]):
            le, lc = _losses(e.parent), _losses(c.parent)
            assert len(le) == len(lc)
            assert le[0] == pytest.approx(lc[0], rel=1e-5)               # the same first step, at rounding
            assert lc[-1] == pytest.approx(le[-1], rel=1e-2)             # and the same training, near enough
            ck = load_checkpoint(c)
            assert ck["config"]["compile"] is True and ck["finished"]
            assert all(torch.isfinite(v).all() for v in ck["model"].values())

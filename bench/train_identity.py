"""Do two checkouts train the same bytes? Solo and stacked runs of both, every tensor compared bit for bit.

    git worktree add /tmp/old REV            # the revision to compare with
    python bench/train_identity.py /tmp/old  # this checkout against it

A refactoring of the trainer must not move results (issue "One Policy interface and one training
implementation"). Each checkout, in its own subprocess (its own ``sdp_cli`` first on ``sys.path``), writes the same
synthetic pendulum datasets and trains with them: one SDP and one DP run alone, and a fig1-shaped stack of 6 runs
(3 seeds x 2 dataset sizes) of each; then the variants of the Sobolev term (vjp mode alone; total path, 2
projections; cap and fraction; the state action), alone and as stacks of 2. Every weight, EMA weight and AdamW
state tensor of every final checkpoint is compared; the script prints how many differ and exits 1 if any does.
Run on one machine (kernels of another CPU round otherwise: docs/artifacts.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

TINY = dict(horizon=8, down_dims=[8, 16], n_groups=4, step_embed_dim=8, batch_size=16, checkpoint_every_s=1e9,
            epochs=4)
FIG1 = dict(horizon=16, down_dims=[16, 32, 32], n_groups=8, step_embed_dim=16, batch_size=16, checkpoint_every_s=1e9,
            epochs=6)
VARIANTS = {"vjp": dict(sobolev_mode="vjp"), "total": dict(sobolev_path="total", sobolev_n_proj=2),
            "cap": dict(sobolev_cap=0.5, sobolev_fraction=0.5), "state": dict(action="x", sobolev_path="total")}


def train_all(checkout: Path, out: Path) -> None:
    """In a subprocess whose ``sys.path`` starts at ``checkout``: train every run, save every tensor."""
    sys.path[:0] = [str(checkout), str(checkout / "tests")]
    import torch

    torch.set_num_threads(1)
    from synthetic_dataset import write_dataset

    from sdp_cli.policy.checkpoint import load_checkpoint
    from sdp_cli.policy.config import TrainConfig
    from sdp_cli.training.train import train
    from sdp_cli.training.train_stack import train_stack

    out.mkdir(parents=True, exist_ok=True)
    data = {n: write_dataset(out / f"p{n}.npz", "pendulum", n_traj=n, seed=n, T=30) for n in (3, 6)}
    quiet = lambda *_: None   # noqa: E731
    cks = {}
    for m in ("sdp", "dp"):
        cks[f"solo-{m}"] = train(data[6], out / f"solo-{m}", TrainConfig.of(method=m, seed=0, **FIG1), device="cpu",
                                 progress=False, log=quiet)
        cfgs = [TrainConfig.of(method=m, seed=s, **FIG1) for n in (3, 6) for s in (0, 1, 2)]
        for i, ck in enumerate(train_stack([data[n] for n in (3, 6) for _ in range(3)],
                                           [out / f"st-{m}-{i}" for i in range(6)], cfgs, log=quiet)):
            cks[f"st-{m}-{i}"] = ck
    for name, v in VARIANTS.items():
        cks[f"solo-{name}"] = train(data[6], out / f"solo-{name}", TrainConfig.of(method="sdp", seed=3, **TINY, **v),
                                    device="cpu", progress=False, log=quiet)
        if name != "vjp":   # (the vjp mode does not stack)
            cfgs = [TrainConfig.of(method="sdp", seed=s, **TINY, **v) for s in (0, 1)]
            for i, ck in enumerate(train_stack([data[3], data[6]], [out / f"st-{name}-{i}" for i in range(2)], cfgs,
                                               log=quiet)):
                cks[f"st-{name}-{i}"] = ck
    tensors = {}
    for run, path in cks.items():
        ck = load_checkpoint(path)
        for key in ("model", "ema_model"):
            tensors.update({f"{run}/{key}.{n}": v for n, v in ck[key].items()})
        for pid, st in ck["train_state"]["optimizer"]["state"].items():
            tensors.update({f"{run}/opt.{pid}.{n}": v for n, v in st.items()})
    torch.save(tensors, out / "tensors.pt")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--train":
        return train_all(Path(sys.argv[2]), Path(sys.argv[3]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("other", type=Path, help="the other checkout (e.g. a git worktree of another revision)")
    a = ap.parse_args()
    here = Path(__file__).resolve().parents[1]
    import torch

    with tempfile.TemporaryDirectory() as tmp:
        got = {}
        for label, checkout in (("this", here), ("other", a.other.resolve())):
            subprocess.run([sys.executable, __file__, "--train", str(checkout), f"{tmp}/{label}"], check=True)
            got[label] = torch.load(f"{tmp}/{label}/tensors.pt")
    mine, theirs = got["this"], got["other"]
    differ = [k for k in mine if k not in theirs or not torch.equal(mine[k], theirs[k])]
    missing = sorted(set(theirs) - set(mine))
    print(f"{len(mine)} tensors of {len({k.split('/')[0] for k in mine})} runs: {len(differ)} differ, "
          f"{len(missing)} only in {a.other}")
    for k in differ[:10]:
        print(f"  differs: {k}")
    sys.exit(1 if differ or missing else 0)


if __name__ == "__main__":
    main()

"""Which CPU kernel settings change what a training run computes? The same `sdp train` (seed, data, 1 torch
thread) is run in fresh processes under each environment below, and the SHA-256 of each checkpoint's tensors is
printed: equal hashes mean the setting does not reach the run's arithmetic on this machine.

    python bench/cpu_bytes.py [--task pendulum] [--n-traj 4] [--epochs 3] [--data DATASET.npz --method dp]

- ``sdp's default``: no variable set, so ``import sdp_cli`` caps oneDNN, MKL and ATen at AVX2
  (:mod:`sdp_cli.kernels`, on a CPU with AVX2);
- ``default again``: the same, in another process (a run is reproducible on one machine);
- ``native ATen`` / ``native MKL`` / ``native oneDNN``: one library uncapped (``ATEN_CPU_CAPABILITY`` set to
  this CPU's level, ``MKL_CBWR=AUTO``, ``ONEDNN_MAX_CPU_ISA=ALL``), the others capped;
- ``native``: all three uncapped, the machine's own kernels (what every run did before 2026-12-04).

On a CPU with AVX-512 a ``native`` hash other than the default's is what separated two machines' runs of one
seed before the cap (docs/artifacts.md, "Same seed, other CPU"). Without ``--data`` a small dataset of ``--task``
is collected first (``sdp collect``, in a temporary folder). Prints the CPU model, its SIMD flags
(:func:`sdp_cli.kernels.cpu_simd`) and torch's CPU capability beside the table.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

#: variables that choose the kernels (cleared in every case's process, then set as the case says)
CLEARED = ("ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_CBWR")


def cases(simd: list[str]) -> dict[str, dict[str, str]]:
    aten = {"ATEN_CPU_CAPABILITY": "avx512" if "avx512f" in simd else "avx2"}
    mkl, onednn = {"MKL_CBWR": "AUTO"}, {"ONEDNN_MAX_CPU_ISA": "ALL"}
    return {"sdp's default": {}, "default again": {}, "native ATen": aten, "native MKL": mkl,
            "native oneDNN": onednn, "native": {**aten, **mkl, **onednn}}


SDP = [sys.executable, "-m", "sdp_cli.cli"]


def weights_sha256(path: Path) -> str:
    """SHA-256 of every tensor of a checkpoint (weights, EMA, optimizer state, normalizer) by key path: the
    arithmetic's result, not the file (whose provenance records the kernel settings themselves)."""
    import torch

    from sdp_cli.policy.checkpoint import load_checkpoint

    h = hashlib.sha256()

    def walk(obj, key: str) -> None:
        if isinstance(obj, torch.Tensor):
            h.update(key.encode())
            h.update(obj.detach().cpu().contiguous().numpy().tobytes())
        elif isinstance(obj, dict):
            for k in sorted(obj, key=str):
                walk(obj[k], f"{key}/{k}")
        elif isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                walk(v, f"{key}/{i}")

    walk({k: v for k, v in load_checkpoint(path).items() if k != "provenance"}, "")
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="pendulum", help="task of the dataset collected when --data is not given")
    ap.add_argument("--n-traj", type=int, default=4)
    ap.add_argument("--data", type=Path, help="a dataset to train on instead (e.g. a run's it0/data.npz)")
    ap.add_argument("--method", default="dp", help="dp or sdp (sdp needs a dataset with gains; collected ones have)")
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--horizon", type=int, help="T_h (default: the trainer's)")
    args = ap.parse_args()

    import torch

    from sdp_cli.data.artifacts import machine
    from sdp_cli.kernels import cpu_simd

    base = {k: v for k, v in os.environ.items() if k not in CLEARED}
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "data.npz"
            subprocess.run(SDP + ["collect", "--task", args.task, "--n-traj", str(args.n_traj), "--seed", "0",
                                  "--out", str(data), "--workers", "1", "--no-progress"],
                           check=True, env=base, stdout=subprocess.DEVNULL)
        rows = []
        for i, (name, extra) in enumerate(cases(cpu_simd()).items()):
            out = Path(tmp) / f"run{i}"
            cmd = SDP + ["train", "--data", str(data), "--out", str(out), "--method", args.method, "--epochs",
                         str(args.epochs), "--seed", "0", "--threads", "1", "--no-progress"]
            if args.horizon:
                cmd += ["--horizon", str(args.horizon)]
            subprocess.run(cmd, check=True, env={**base, **extra}, stdout=subprocess.DEVNULL)
            rows.append((name, weights_sha256(out / "checkpoint.pt")))
    ref = rows[0][1]
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine()['cpu_model']}, "
          f"SIMD flags {','.join(cpu_simd()) or '-'}, torch {torch.__version__} (CPU capability under sdp's "
          f"default: {torch.backends.cpu.get_cpu_capability()})")
    print(f"# sdp train --method {args.method} --epochs {args.epochs} --seed 0 --threads 1 on "
          f"{args.data or f'{args.task}, {args.n_traj} trajectories (sdp collect --seed 0)'}")
    print("| environment | tensors' SHA-256 (first 16) | same tensors as sdp's default |")
    print("|---|---|---|")
    for name, h in rows:
        print(f"| {name} | {h[:16]} | {'yes' if h == ref else 'no'} |")


if __name__ == "__main__":
    main()

"""Which CPU kernel settings change the bytes a training run writes? The same `sdp train` (seed, data, 1 torch
thread) is run in fresh processes under each environment below, and the SHA-256 of each checkpoint is printed:
equal hashes mean the setting does not reach the run's arithmetic on this machine.

    python bench/cpu_bytes.py [--task pendulum] [--n-traj 4] [--epochs 3] [--data DATASET.npz --method dp]

- ``default``: no variable set (the kernels of this machine's CPU);
- ``default again``: the same, in another process (a run is reproducible on one machine);
- ``ATEN_CPU_CAPABILITY=avx2``: ATen's own vectorised loops capped at AVX2;
- ``MKL_ENABLE_INSTRUCTIONS=AVX2``: MKL (matrix products) capped at AVX2;
- ``ONEDNN_MAX_CPU_ISA=AVX2``: oneDNN (torch's CPU convolutions) capped at AVX2;
- all three together.

On a CPU with AVX-512 a hash that changes under a cap at AVX2 is what another machine without AVX-512 would write
(docs/artifacts.md, "Same seed, other CPU"). Without ``--data`` a small dataset of ``--task`` is collected first
(``sdp collect``, in a temporary folder). Prints the CPU model, its SIMD flags
(:func:`sdp_cli.data.artifacts.cpu_simd`) and torch's CPU capability beside the table.
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

CASES = {
    "default": {},
    "default again": {},
    "ATEN_CPU_CAPABILITY=avx2": {"ATEN_CPU_CAPABILITY": "avx2"},
    "MKL_ENABLE_INSTRUCTIONS=AVX2": {"MKL_ENABLE_INSTRUCTIONS": "AVX2"},
    "ONEDNN_MAX_CPU_ISA=AVX2": {"ONEDNN_MAX_CPU_ISA": "AVX2"},
    "all three": {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"},
}
#: variables that would change the kernels under a case (cleared in every case's process)
CLEARED = ("ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_CBWR")
SDP = [sys.executable, "-m", "sdp_cli.cli"]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


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

    from sdp_cli.data.artifacts import cpu_simd, machine

    base = {k: v for k, v in os.environ.items() if k not in CLEARED}
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "data.npz"
            subprocess.run(SDP + ["collect", "--task", args.task, "--n-traj", str(args.n_traj), "--seed", "0",
                                  "--out", str(data), "--workers", "1", "--no-progress"],
                           check=True, env=base, stdout=subprocess.DEVNULL)
        rows = []
        for i, (name, extra) in enumerate(CASES.items()):
            out = Path(tmp) / f"run{i}"
            cmd = SDP + ["train", "--data", str(data), "--out", str(out), "--method", args.method, "--epochs",
                         str(args.epochs), "--seed", "0", "--threads", "1", "--no-progress"]
            if args.horizon:
                cmd += ["--horizon", str(args.horizon)]
            subprocess.run(cmd, check=True, env={**base, **extra}, stdout=subprocess.DEVNULL)
            rows.append((name, sha256(out / "checkpoint.pt")))
    ref = rows[0][1]
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine()['cpu_model']}, "
          f"SIMD flags {','.join(cpu_simd()) or '-'}, torch {torch.__version__} CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}")
    print(f"# sdp train --method {args.method} --epochs {args.epochs} --seed 0 --threads 1 on "
          f"{args.data or f'{args.task}, {args.n_traj} trajectories (sdp collect --seed 0)'}")
    print("| environment | checkpoint SHA-256 (first 16) | same bytes as default |")
    print("|---|---|---|")
    for name, h in rows:
        print(f"| {name} | {h[:16]} | {'yes' if h == ref else 'no'} |")


if __name__ == "__main__":
    main()

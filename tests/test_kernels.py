"""CPU kernels capped at AVX2 (sdp_cli/kernels.py): the same seed trains the same weights on any x86 CPU with AVX2.

Measured 2026-12-04 (`python bench/cpu_bytes.py`, AMD EPYC with AVX-512): oneDNN's own kernel choice changed a
run's weights; fig4's quadrotor-0 DP seed 0 scored 637 there against 627 from an earlier machine, and `dvc repro`
of the small experiment gave SDP 22.26 against the committed 18.47 until oneDNN was capped at AVX2 (then 18.47,
every row as committed). The cap must be in effect before torch runs its first convolution: `import sdp_cli` sets
it, and the CLI, the pipeline's workers and the tests all import sdp_cli first."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sdp_cli.kernels import PORTABLE, cap_cpu_kernels, compile_cache_dir, cpu_kernels, cpu_simd

#: trains a tiny SDP policy (seed 0, 1 thread) in a fresh process and prints the SHA-256 of its EMA weights
TRAIN = """
import hashlib, sys
import sdp_cli
from sdp_cli.policy.checkpoint import load_checkpoint
from sdp_cli.policy.config import TrainConfig
from sdp_cli.training.train import train
import torch
torch.set_num_threads(1)
cfg = TrainConfig.of(method="sdp", epochs=4, horizon=8, down_dims=[16, 32], n_groups=4, step_embed_dim=8,
                     batch_size=8, checkpoint_every_s=1e9)
train(sys.argv[1], sys.argv[2], cfg, device="cpu", progress=False, log=lambda *_: None)
ck = load_checkpoint(sys.argv[2])
h = hashlib.sha256()
for k, v in sorted({**ck["model"], **{"ema." + k: v for k, v in (ck["ema_model"] or {}).items()}}.items()):
    h.update(k.encode()); h.update(v.numpy().tobytes())
print(h.hexdigest())
"""


def test_cap_sets_what_the_user_left_unset_and_only_on_avx2():
    env = {"ONEDNN_MAX_CPU_ISA": "ALL"}
    assert cap_cpu_kernels(env, simd=["avx2", "fma"]) == {**PORTABLE, "ONEDNN_MAX_CPU_ISA": "ALL"}
    assert env == {**PORTABLE, "ONEDNN_MAX_CPU_ISA": "ALL"}        # the user's choice wins
    bare: dict[str, str] = {}
    assert cap_cpu_kernels(bare, simd=[]) == {} and bare == {}      # no AVX2 (another architecture): nothing
    assert cap_cpu_kernels(bare, simd=["avx2"]) == {} and bare == {}  # AVX2 without FMA: OpenBLAS's Haswell needs it
    assert cpu_kernels({"MKL_CBWR": "AUTO", "PATH": "/bin"}) == {"MKL_CBWR": "AUTO"}


def test_cpu_simd_reads_the_first_cpus_flags_in_a_fixed_order():
    info = ("processor\t: 0\nmodel name\t: X\nflags\t\t: fpu sse2 avx512_bf16 avx2 fma avx512f lm\n\n"
            "processor\t: 1\nflags\t\t: fpu amx_tile\n")
    assert cpu_simd(info) == ["avx2", "fma", "avx512f", "avx512_bf16"]
    assert cpu_simd("flags\t: fpu sse sse2\n") == []
    assert cpu_simd("processor\t: 0\n") == []      # no flags line (another OS's format)


def test_importing_sdp_cli_caps_a_fresh_process_and_artifacts_record_it(tmp_path):
    if "avx2" not in cpu_simd():
        pytest.skip("the cap applies on x86 CPUs with AVX2 only")
    env = {k: v for k, v in os.environ.items() if k not in PORTABLE}
    code = ("import json, os, sys, numpy as np, sdp_cli\n"
            "from sdp_cli.data.artifacts import save_npz, load_npz\n"
            "_, meta = load_npz(save_npz(sys.argv[1], {'x': np.zeros(2)}, kind='dataset'))\n"
            "print(json.dumps([{k: os.environ.get(k) for k in sdp_cli.kernels.PORTABLE}, "
            "meta['provenance']['cpu_kernels']]))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "a.npz")], env=env, capture_output=True,
                         text=True, check=True).stdout
    assert json.loads(out) == [PORTABLE, PORTABLE]


def test_compiled_runs_cache_where_the_docs_say_even_after_diffusers_imports_dynamo(tmp_path):
    """Importing diffusers imports torch._dynamo, which fixes inductor's cache folder to /tmp/torchinductor_<user>
    when TORCHINDUCTOR_CACHE_DIR is unset: until 2026-12-06 every compiled run cached there, not in the shared
    folder of sdp_cli.policy.compiling. `import sdp_cli` sets it first; a folder the user set wins."""
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHINDUCTOR_CACHE_DIR", "SDP_COMPILE_CACHE")}
    code = ("import sdp_cli.policy.diffusion\n"
            "from torch._inductor.runtime.cache_dir_utils import cache_dir\nprint(cache_dir())")
    run = lambda **e: subprocess.run([sys.executable, "-c", code], env={**env, **e}, capture_output=True,   # noqa: E731
                                     text=True, check=True).stdout.strip()
    assert run(SDP_COMPILE_CACHE=str(tmp_path / "c")) == str(tmp_path / "c")
    assert run(SDP_COMPILE_CACHE=str(tmp_path / "c"), TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "t")) == str(tmp_path / "t")
    assert compile_cache_dir({"XDG_CACHE_HOME": "/x"}) == Path("/x/sdp/inductor")
    assert compile_cache_dir({"XDG_CACHE_HOME": "/x", "SDP_COMPILE_CACHE": "/c"}) == Path("/c")


def test_numpy_imported_after_sdp_cli_runs_openblas_at_the_avx2_level():
    """A policy's rollout goes through numpy: before the cap, OpenBLAS's AVX-512 kernels moved quadrotor-0's rollout
    costs in the ninth digit and the refined cost by 3% (docs/artifacts.md); the default must be Haswell's."""
    if "avx512f" not in cpu_simd():
        pytest.skip("needs a CPU with AVX-512, where OpenBLAS's own kernels differ from AVX2's")
    code = ("import sys, hashlib\nif sys.argv[1] == 'sdp': import sdp_cli\nimport numpy as np\n"
            "r = np.random.default_rng(0); a = r.standard_normal((64, 257)); b = r.standard_normal((257, 33))\n"
            "print(hashlib.sha256((a @ b).tobytes() + (a @ b[:, 0]).tobytes()).hexdigest())")
    base = {k: v for k, v in os.environ.items() if k not in PORTABLE}

    def run(first, **extra):
        return subprocess.run([sys.executable, "-c", code, first], env={**base, **extra}, capture_output=True,
                              text=True, check=True).stdout.strip()

    default = run("sdp")
    assert default == run("numpy", OPENBLAS_CORETYPE="Haswell")
    assert default != run("numpy", OPENBLAS_CORETYPE="SkylakeX")


def test_training_under_the_default_cap_computes_what_an_explicit_avx2_cap_does(tmp_path):
    """Catches a cap set too late (after torch chose its kernels) or not at all: on a CPU with AVX-512 the
    machine's own oneDNN kernels give other weights, and the default must give the capped ones."""
    simd = cpu_simd()
    if "avx512f" not in simd:
        pytest.skip("needs a CPU with AVX-512, where oneDNN's own kernels differ from AVX2's")
    from synthetic_dataset import write_dataset

    data = write_dataset(tmp_path / "p.npz", "pendulum", n_traj=3, seed=0, T=30)
    base = {k: v for k, v in os.environ.items() if k not in PORTABLE}

    def weights(name, **extra):
        return subprocess.run([sys.executable, "-c", TRAIN, str(data), str(tmp_path / name)], env={**base, **extra},
                              capture_output=True, text=True, check=True).stdout.strip()

    default = weights("default")
    assert default == weights("capped", **PORTABLE)
    assert default != weights("native", ONEDNN_MAX_CPU_ISA="ALL")

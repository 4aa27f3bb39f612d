"""CPU kernels capped at one instruction-set level, so that a seed gives the same numbers on any x86 CPU.

torch's CPU convolutions (oneDNN), its matrix products (MKL), its own vectorised loops (ATen) and numpy's
OpenBLAS choose their kernels by the CPU's SIMD level, and kernels of another level round otherwise: the same
seed trained other weights (oneDNN), and rolled a policy out to other states (OpenBLAS), on a CPU with AVX-512
than on one with AVX2 only (docs/artifacts.md, "Same seed, other CPU"; ``python bench/cpu_bytes.py``).
``import sdp_cli`` calls :func:`cap_cpu_kernels`: where the CPU has AVX2 and FMA, each variable of
:data:`PORTABLE` the user has not set is set to the AVX2 level; one the user set wins (``ONEDNN_MAX_CPU_ISA=ALL``:
oneDNN's own choice). torch reads its variables when it first runs such a kernel and OpenBLAS when numpy is
imported, so a program that ran torch or imported numpy before importing sdp_cli exports them itself. Artifacts
record the values in effect (``provenance.cpu_kernels``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import MutableMapping

#: the variables and the level they are capped at (oneDNN, MKL's conditional numerical reproducibility, ATen,
#: OpenBLAS's kernels for AVX2 + FMA CPUs)
PORTABLE = {"ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2",
            "OPENBLAS_CORETYPE": "Haswell"}

#: CPU flags that decide which kernels those libraries run (recorded in every timing sidecar)
SIMD_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_tile", "amx_bf16")


def cpu_simd(cpuinfo: str | None = None) -> list[str]:
    """The :data:`SIMD_FLAGS` of the first CPU in ``cpuinfo`` (default: /proc/cpuinfo; empty where it cannot be
    read, e.g. not on Linux), in :data:`SIMD_FLAGS`' order."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            return []
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            have = set(line.split(":", 1)[1].split())
            return [f for f in SIMD_FLAGS if f in have]
    return []


def cap_cpu_kernels(environ: MutableMapping[str, str] = os.environ, simd: list[str] | None = None) -> dict[str, str]:
    """Set each :data:`PORTABLE` variable that ``environ`` lacks, where the CPU has AVX2 and FMA (``simd``: its
    flags, default :func:`cpu_simd`); nothing on a CPU without them (another architecture: the values name x86
    kernels). Returns :func:`cpu_kernels` of ``environ``."""
    if {"avx2", "fma"} <= set(cpu_simd() if simd is None else simd):
        for k, v in PORTABLE.items():
            environ.setdefault(k, v)
    return cpu_kernels(environ)


def cpu_kernels(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """The :data:`PORTABLE` variables set in ``environ`` (by :func:`cap_cpu_kernels` or by the user)."""
    return {k: environ[k] for k in PORTABLE if k in environ}


#: the variable naming the folder where inductor keeps what ``torch.compile`` compiled (:mod:`sdp_cli.policy.compiling`)
COMPILE_CACHE_ENV = "SDP_COMPILE_CACHE"


def compile_cache_dir(environ: MutableMapping[str, str] = os.environ) -> Path:
    """The inductor cache folder of this machine's runs: ``$SDP_COMPILE_CACHE``, else
    ``$XDG_CACHE_HOME/sdp/inductor``, else ``~/.cache/sdp/inductor``."""
    if environ.get(COMPILE_CACHE_ENV):
        return Path(environ[COMPILE_CACHE_ENV])
    base = Path(environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "sdp" / "inductor"


def use_compile_cache(environ: MutableMapping[str, str] = os.environ) -> None:
    """Point inductor at :func:`compile_cache_dir` unless the user set ``TORCHINDUCTOR_CACHE_DIR``. Called at
    ``import sdp_cli``: importing ``torch._dynamo`` (diffusers does) fixes inductor's folder to its default,
    /tmp/torchinductor_<user>, when the variable is unset, so setting it at the first compile came too late
    (until 2026-12-06 every compiled run cached there)."""
    environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(compile_cache_dir(environ)))

"""torch's CPU kernels capped at one instruction-set level, so that a seed trains the same bytes on any x86 CPU.

torch's CPU convolutions (oneDNN), its matrix products (MKL) and its own vectorised loops (ATen) choose their
kernels by the CPU's SIMD level, and kernels of another level round otherwise: the same seed trained other
weights on a CPU with AVX-512 than on one with AVX2 only (docs/artifacts.md, "Same seed, other CPU";
``python bench/cpu_bytes.py``). ``import sdp_cli`` calls :func:`cap_cpu_kernels`: where the CPU has AVX2, each
variable of :data:`PORTABLE` the user has not set is set to AVX2; one the user set wins (``ONEDNN_MAX_CPU_ISA=ALL``:
the machine's own kernels). torch reads them when it first runs such a kernel, so a program that ran torch
before importing sdp_cli exports them itself. Artifacts record the values in effect (``provenance.cpu_kernels``).
"""

from __future__ import annotations

import os
from typing import MutableMapping

#: the variables and the level they are capped at (oneDNN, MKL's conditional numerical reproducibility, ATen)
PORTABLE = {"ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"}

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
    """Set each :data:`PORTABLE` variable that ``environ`` lacks, where the CPU has AVX2 (``simd``: its flags,
    default :func:`cpu_simd`); nothing on a CPU without it (another architecture: these libraries are x86's).
    Returns :func:`cpu_kernels` of ``environ``."""
    if "avx2" in (cpu_simd() if simd is None else simd):
        for k, v in PORTABLE.items():
            environ.setdefault(k, v)
    return cpu_kernels(environ)


def cpu_kernels(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """The :data:`PORTABLE` variables set in ``environ`` (by :func:`cap_cpu_kernels` or by the user)."""
    return {k: environ[k] for k in PORTABLE if k in environ}

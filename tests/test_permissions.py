"""Artifacts, checkpoints and CSVs get the usual permissions (0644 under umask 022), not mkstemp's 0600,
and record the runtime (torch threads, CPU model) in their provenance."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from sdp_cli.data.artifacts import atomic_write_bytes, load_npz, save_npz


@pytest.fixture()
def umask022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_artifacts_have_umask_permissions(tmp_path, umask022):
    a = save_npz(tmp_path / "a.npz", {"x": np.zeros(2)}, kind="dataset")
    c = atomic_write_bytes(tmp_path / "m.csv", lambda f: f.write(b"a,b\n"))
    for p in (a, c):
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, oct(p.stat().st_mode)
    os.umask(0o077)
    p = save_npz(tmp_path / "b.npz", {"x": np.zeros(2)}, kind="dataset")
    assert stat.S_IMODE(p.stat().st_mode) == 0o600


def test_provenance_records_threads_and_cpu(tmp_path):
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _, meta = load_npz(save_npz(tmp_path / "a.npz", {"x": np.zeros(2)}, kind="dataset"))
    finally:
        torch.set_num_threads(n)
    prov = meta["provenance"]
    assert prov["torch_threads"] == 1 and "git_rev" in prov
    # the machine (CPU, kernel) is in the timing sidecar, not in the artifact's bytes: the same run on
    # another machine writes the same bytes
    from sdp_cli.data.artifacts import load_timing

    assert "cpu_model" not in prov and "platform" not in prov
    rec = load_timing(tmp_path / "a.npz")["machine"]
    assert rec["cpu_model"]
    # the instruction sets that decide a training run's last bits (docs/artifacts.md), beside the CPU model
    from sdp_cli.kernels import cpu_simd

    assert rec["cpu_simd"] == cpu_simd() and rec["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert "cpu_simd" not in prov and "torch_cpu_capability" not in prov


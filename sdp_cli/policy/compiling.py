"""``torch.compile`` for training (``TrainConfig.compile``, ``sdp train --compile``): the network's calls compiled by
inductor, with one persistent cache per machine that every run of the same shapes shares.

A cold compile of the U-Net's forward and tangent pass costs minutes of CPU (``bench/compile_train.py``); inductor
keeps what it compiled in its cache folder, here ``$SDP_COMPILE_CACHE`` (default ``$XDG_CACHE_HOME/sdp/inductor``,
else ``~/.cache/sdp/inductor``) unless ``TORCHINDUCTOR_CACHE_DIR`` is set (set at ``import sdp_cli``: :func:`sdp_cli.kernels.use_compile_cache`), so the next run of the same shapes, in
any process, loads it in seconds. Inductor's generated kernels follow ``ATEN_CPU_CAPABILITY``, which
:mod:`sdp_cli.kernels` caps at AVX2, so a compiled run gives the same numbers on other x86 CPUs too.
"""

from __future__ import annotations

from sdp_cli.kernels import COMPILE_CACHE_ENV as CACHE_ENV, compile_cache_dir as cache_dir

__all__ = ["CACHE_ENV", "cache_dir", "compiled"]


def compiled(fn):
    """``torch.compile(fn)`` (inductor, the default mode) with the shared cache in effect; compiles at its first
    call, again for a new input shape (a smaller last batch of an epoch)."""
    import torch

    return torch.compile(fn)     # (the cache folder is set at ``import sdp_cli``: use_compile_cache)

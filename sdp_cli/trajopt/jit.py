"""On-disk cache of compiled casadi functions (C code generation + gcc).

casadi evaluates symbolic functions in a virtual machine; compiling the generated C code
roughly halves the solve time of the trajectory optimizer. Compiling costs a few seconds,
so the shared libraries are kept in a cache folder that survives across runs:

- folder: ``$SDP_CACHE_DIR`` (default ``~/.cache/sdp``), subfolder ``jit/``;
- key: SHA-256 of the generated C source, the compiler command and the casadi version,
  so any change of the problem (task, horizon, solver plugin) gives a new library;
- writes are atomic (compile to a temporary name, then ``os.replace``), so concurrent
  processes can share the folder.

Compilation is optional: :func:`compile_functions` returns ``None`` (and warns once)
when gcc is missing or fails, and the caller falls back to casadi's virtual machine.
Set ``SDP_JIT=0`` to disable it globally. ``SDP_JIT_OPT`` sets gcc's optimization level (``-O2`` by default;
``-O0`` compiles the quadrotor's and UR5's functions 5-12x faster and runs them 2.2-2.7x slower, measured
2026-12-07 on this project's 2-core Intel Xeon; the default test suite uses it, tests/conftest.py). No level
reassociates floating-point operations, and without ``-march`` gcc emits no fused multiply-add, so ``-O0`` and
``-O2`` compute the same bits (tests/test_trajopt.py::test_every_optimization_level_computes_the_same_bits); the
level is part of the cache key.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca

from sdp_cli.errors import SdpError

log = logging.getLogger(__name__)

#: compiler flags besides the optimization level (the source and output paths are appended)
CFLAGS = ("-fPIC", "-shared")
#: the optimization levels ``SDP_JIT_OPT`` may name
OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3")


def opt_level() -> str:
    """gcc's optimization level: ``$SDP_JIT_OPT`` (one of :data:`OPT_LEVELS`), ``-O2`` by default."""
    opt = os.environ.get("SDP_JIT_OPT", "").strip() or "-O2"
    if opt not in OPT_LEVELS:
        raise SdpError(f"SDP_JIT_OPT={opt!r}: expected one of {', '.join(OPT_LEVELS)}")
    return opt


def cache_dir() -> Path:
    """The sdp cache folder: ``$SDP_CACHE_DIR`` or ``~/.cache/sdp``."""
    return Path(os.environ.get("SDP_CACHE_DIR") or "~/.cache/sdp").expanduser()


def jit_enabled_by_default() -> bool:
    """``False`` when the environment sets ``SDP_JIT=0`` (or ``false``/``no``/``off``)."""
    return os.environ.get("SDP_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


@functools.cache
def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")


_warned: set[str] = set()


def _warn_once(msg: str) -> None:
    if msg not in _warned:
        _warned.add(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def compile_functions(name: str, functions: list[ca.Function]) -> ca.Importer | None:
    """Generate C code for ``functions``, compile (or reuse) the library, load it.

    Returns a casadi ``Importer`` of the shared library (pass it to ``ca.nlpsol`` or
    ``ca.external``), or ``None`` if compilation is impossible.
    """
    cc = _compiler()
    if cc is None:
        _warn_once("sdp: no C compiler found, casadi functions are not compiled (slower solves)")
        return None
    flags = (opt_level(), *CFLAGS)
    gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    for f in functions:
        gen.add(f)
    with tempfile.TemporaryDirectory(prefix="sdp_jit_") as tmp:
        gen.generate(tmp + os.sep)
        src = Path(tmp) / f"{name}.c"
        code = src.read_bytes()
        key = hashlib.sha256(code + repr((cc, flags, ca.__version__)).encode()).hexdigest()[:20]
        out_dir = cache_dir() / "jit"
        lib = out_dir / f"{name}_{key}.so"
        if not lib.is_file():
            log.info("compiling %s (%.1f MB of C, one-off; cached as %s)", name, len(code) / 1e6, lib)
            try:
                out_dir.mkdir(parents=True, exist_ok=True)
                fd, tmp_lib = tempfile.mkstemp(prefix=f".{lib.name}.", suffix=".tmp", dir=out_dir)
                os.close(fd)
                proc = subprocess.run([cc, *flags, str(src), "-o", tmp_lib, "-lm"],
                                      capture_output=True, text=True)
                if proc.returncode != 0:
                    Path(tmp_lib).unlink(missing_ok=True)
                    _warn_once(f"sdp: compiling casadi functions failed, using the casadi virtual "
                               f"machine instead: {proc.stderr.strip()[:300]}")
                    return None
                os.replace(tmp_lib, lib)
            except OSError as e:
                _warn_once(f"sdp: cannot write the JIT cache in {out_dir} ({e}); not compiling")
                return None
    try:
        return ca.Importer(str(lib), "dll")
    except RuntimeError as e:
        _warn_once(f"sdp: cannot load compiled library {lib} ({e}); not compiling")
        return None

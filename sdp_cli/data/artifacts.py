"""Versioned on-disk artifacts: ``.npz`` files with a JSON metadata record.

Every artifact sdp writes is a NumPy ``.npz`` archive (open it with ``np.load`` without
sdp). Besides its arrays it holds ``__meta__``: a 0-d string array with a JSON object
that has at least ``kind`` (e.g. ``"dataset"``), ``format_version``,
``provenance`` (package versions, git revision, python, platform) and ``config``.
The array layout of each kind is documented in ``docs/artifacts.md``.

Same inputs, same bytes: an artifact holds no clock readings, so re-running a DVC stage with
nothing changed leaves ``dvc.lock`` as it was. What was timed (solve, rollout, training and
wall times) and when the file was written go to a sidecar ``<stem>.timing.json`` next to it
(:func:`save_timing` / :func:`load_timing`), which is not a DVC output.

Writes are atomic (temporary file in the same folder, fsync, ``os.replace``), so a
killed process never leaves a half-written artifact.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import os
import platform
import subprocess
import tempfile
import zipfile
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from sdp_cli.errors import SdpError
from sdp_cli.kernels import cpu_kernels, cpu_simd

FORMAT_VERSION = 1
_PACKAGES = ("sdp-cli", "numpy", "casadi", "pin", "example-robot-data", "torch", "diffusers")


#: repository paths written by runs; changes there do not make the source tree dirty
GENERATED_PATHS = ("results", "runs", "dvc.lock")


@functools.cache
def git_revision() -> str:
    """``git rev-parse HEAD`` of the source tree (with ``+dirty`` when modified), or ``unknown``.

    Outputs of runs that live in the repository (``GENERATED_PATHS``: ``results/``, ``runs/``,
    ``dvc.lock``) do not count as modifications: a report written into ``results/`` is still
    from a clean tree.
    """
    return revision_of(Path(__file__).resolve().parents[2])


#: the paths whose content makes the code: an artifact records the last commit that changed them
CODE_PATHS = ("sdp_cli", "pyproject.toml")


@functools.cache
def code_revision() -> str:
    """The last commit that changed the code (``CODE_PATHS``), with ``+dirty`` when they hold
    uncommitted changes, or ``unknown``: what artifacts and manifests record, so that a commit of
    results, docs or tests does not change an artifact's bytes (a DVC re-run at a later commit with
    the same code writes the same files), while any code change does."""
    return code_revision_of(Path(__file__).resolve().parents[2])


def code_revision_of(root: Path) -> str:
    """:func:`code_revision` of the git work tree at ``root``."""
    try:
        rev = subprocess.run(["git", "log", "-1", "--format=%H", "--", *CODE_PATHS], cwd=root,
                             capture_output=True, text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS],
                               cwd=root, capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "unknown") + ("+dirty" if dirty and rev else "")


def revision_of(root: Path) -> str:
    """:func:`git_revision` of the git work tree at ``root``."""
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "."]
                               + [f":(exclude){p}" for p in GENERATED_PATHS], cwd=root,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@functools.cache
def provenance() -> dict[str, Any]:
    """Package versions, git revision of the code (:func:`code_revision`) and Python version, recorded
    inside every artifact. What differs between machines running the same code (the CPU model, the kernel:
    :func:`machine`) goes to the timing sidecar instead, so that the same run on another machine writes the
    same bytes (DVC's hashes, and the committed dvc.lock, then agree)."""
    versions = {}
    for pkg in _PACKAGES:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return {"versions": versions, "git_rev": code_revision(), "python": platform.python_version()}


def machine() -> dict[str, Any]:
    """The machine that wrote an artifact, kept in its timing sidecar: platform (kernel), CPU model, the CPU's
    :data:`~sdp_cli.kernels.SIMD_FLAGS` it has (``cpu_simd``) and, when torch is loaded, the vector level ATen
    dispatches to (capped at AVX2 by default: :mod:`sdp_cli.kernels`)."""
    import sys

    info = _cpuinfo()
    out: dict[str, Any] = {"platform": platform.platform(), "cpu_model": _cpu_model(info),
                           "cpu_simd": cpu_simd(info)}
    torch = sys.modules.get("torch")
    if torch is not None:
        out["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return out


@functools.lru_cache(maxsize=1)
def _cpuinfo() -> str:
    """/proc/cpuinfo, read once per process (empty where it cannot be read, e.g. not on Linux)."""
    try:
        with open("/proc/cpuinfo") as f:
            return f.read()
    except OSError:
        return ""


def _cpu_model(cpuinfo: str) -> str:
    for line in cpuinfo.splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def runtime_provenance() -> dict[str, Any]:
    """:func:`provenance` plus what can change within a process: the CPU kernel caps in effect
    (:mod:`sdp_cli.kernels`), torch's CPU thread count and the CUDA device (when torch is loaded). Timing-free:
    equal for equal settings."""
    import sys

    out = dict(provenance())
    out["cpu_kernels"] = cpu_kernels()
    torch = sys.modules.get("torch")
    if torch is not None:
        out["torch_threads"] = torch.get_num_threads()
        out["cuda_device"] = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    return out


def json_default(o):
    """``json.dumps`` default for artifact metadata: numpy scalars and arrays, paths."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (artifacts that belong together record each other's)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def portable_path(path: str | os.PathLike, base: str | os.PathLike) -> str:
    """``path`` relative to the folder ``base`` (POSIX separators), for recording inside an artifact
    that lives in ``base``: moving or cloning the whole tree then leaves the artifact's bytes unchanged
    (an absolute path would make a ``dvc repro`` in another clone hash differently)."""
    return Path(os.path.relpath(Path(path).resolve(), Path(base).resolve())).as_posix()


def resolve_recorded(path: str | None, base: str | os.PathLike) -> Path | None:
    """A path recorded by :func:`portable_path` (or an older absolute one), made absolute against
    ``base``, the folder of the artifact that recorded it; None stays None."""
    return (Path(base) / path).resolve() if path else None


def ensure_dir(path: str | os.PathLike, what: str) -> Path:
    """Create the output folder ``path`` (``what``: e.g. "run folder") or raise one clear ``SdpError``."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SdpError(f"cannot create the {what} {path}: {e.strerror or e}") from None
    if not os.access(path, os.W_OK):
        raise SdpError(f"cannot write into the {what} {path}: permission denied")
    return path


def check_writable(*paths: str | os.PathLike | None) -> None:
    """``SdpError`` unless every output path's folder can be created and written (before any work)."""
    for p in paths:
        if p is None:
            continue
        parent = Path(p).parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SdpError(f"cannot write {p}: {e.strerror or e}") from None
        if not os.access(parent, os.W_OK) or Path(p).is_dir():
            raise SdpError(f"cannot write {p}: {'it is a folder' if Path(p).is_dir() else 'permission denied'}")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike, writer) -> Path:
    """Call ``writer(fileobj)`` on a temp file next to ``path``, then rename it into place."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise SdpError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())   # mkstemp makes 0600; artifacts get the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], kind: str,
             config: dict[str, Any] | None = None, timing: dict[str, Any] | None = None,
             **extra_meta: Any) -> Path:
    """Atomically write ``arrays`` plus a metadata record of ``kind`` to ``path``; ``timing``
    (measured times, if any) goes to the sidecar :func:`timing_path` instead."""
    meta = {"kind": kind, "format_version": FORMAT_VERSION,
            "provenance": runtime_provenance(), "config": config or {}, **extra_meta}
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.array(json.dumps(meta, default=json_default))
    out = atomic_write_bytes(path, lambda f: _write_npz(f, payload))
    save_timing(path, timing or {})     # clock readings and the machine (outside the hashed bytes)
    return out


def _write_npz(f, payload: dict[str, np.ndarray]) -> None:
    """``np.savez`` with a fixed entry timestamp (the zip format records one per entry)."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for k, v in payload.items():
            info = zipfile.ZipInfo(f"{k}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with z.open(info, "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, v, allow_pickle=False)


def split_timing(record: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(rest, timing)``: the entries named ``*_time`` (clock readings) and the others."""
    timing = {k: v for k, v in record.items() if k.endswith("_time")}
    return {k: v for k, v in record.items() if k not in timing}, timing


def timing_path(path: str | os.PathLike) -> Path:
    """The timing sidecar of an artifact: ``data.npz`` -> ``data.timing.json``, a run folder
    ``policy`` -> ``policy.timing.json`` (next to it, outside a folder that is a DVC output)."""
    p = Path(path)
    return p.with_name((p.stem if p.suffix else p.name) + ".timing.json")


def save_timing(path: str | os.PathLike, timing: dict[str, Any]) -> Path:
    """Write the timing sidecar of ``path`` (adds ``created``, the UTC time of writing)."""
    rec = {"created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
           **timing}
    data = json.dumps(rec, default=json_default, indent=1).encode()
    return atomic_write_bytes(timing_path(path), lambda f: f.write(data))


def load_timing(path: str | os.PathLike) -> dict[str, Any]:
    """The timing sidecar of ``path``; empty when it is missing or unreadable (timings are
    informative, never needed to load the artifact itself)."""
    try:
        rec = json.loads(timing_path(path).read_text())
    except (OSError, ValueError):
        return {}
    return rec if isinstance(rec, dict) else {}


def load_npz(path: str | os.PathLike, kind: str | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read an artifact; ``SdpError`` if missing, corrupt, or not of ``kind``."""
    path = Path(path)
    if not path.is_file():
        raise SdpError(f"artifact not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        # numpy's own text may advise loading with allow_pickle: never pass that on
        raise SdpError(f"corrupt artifact {path}: expected an sdp .npz archive of numeric arrays "
                       f"({type(e).__name__})") from None
    if "__meta__" not in arrays:
        raise SdpError(f"corrupt artifact {path}: no __meta__ record (not written by sdp?)")
    return arrays, _check_meta(path, arrays.pop("__meta__"), kind)


def load_meta(path: str | os.PathLike, kind: str | None = None) -> dict[str, Any]:
    """An artifact's metadata record only (the arrays are not read); errors as :func:`load_npz`."""
    path = Path(path)
    if not path.is_file():
        raise SdpError(f"artifact not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "__meta__" not in z.files:
                raise SdpError(f"corrupt artifact {path}: no __meta__ record (not written by sdp?)")
            raw = z["__meta__"]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise SdpError(f"corrupt artifact {path}: expected an sdp .npz archive of numeric arrays "
                       f"({type(e).__name__})") from None
    return _check_meta(path, raw, kind)


def _check_meta(path: Path, raw, kind: str | None) -> dict[str, Any]:
    try:
        meta = json.loads(str(raw))
    except json.JSONDecodeError as e:
        raise SdpError(f"corrupt artifact {path}: bad metadata ({e})") from None
    if not isinstance(meta, dict):
        raise SdpError(f"corrupt artifact {path}: its metadata is not a JSON object")
    if kind is not None and meta.get("kind") != kind:
        raise SdpError(f"{path} is a {meta.get('kind')!r} artifact, expected {kind!r}")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise SdpError(f"{path} has format_version {meta['format_version']}, newer than this sdp "
                       f"({FORMAT_VERSION}); upgrade sdp")
    return meta

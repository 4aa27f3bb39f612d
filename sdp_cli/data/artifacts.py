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
killed process never leaves a half-written artifact; only regular files are written (an existing device,
fifo, socket or folder at an output path is refused, never replaced). An artifact made of several files
(the ``.npz`` and its sidecar; a checkpoint with its metrics and timing) is written inside
:func:`artifact_writes`: if any of its writes fails (a full disk, a read-only file system) or the process is
interrupted between them, the files it already wrote are removed and those it replaced are restored, so the
folder holds the artifact as it was before, never a part of the new one.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import os
import platform
import subprocess
import zipfile
from importlib import metadata
from pathlib import Path
from typing import Any
import sys
import hashlib

import numpy as np

from sdp_cli.data.writes import (artifact_writes, atomic_write_bytes, check_folder, check_regular,  # noqa: F401
                                 check_writable, ensure_dir)
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


def save_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray], kind: str,
             config: dict[str, Any] | None = None, timing: dict[str, Any] | None = None,
             **extra_meta: Any) -> Path:
    """Atomically write ``arrays`` plus a metadata record of ``kind`` to ``path``; ``timing``
    (measured times, if any) goes to the sidecar :func:`timing_path` instead."""
    meta = {"kind": kind, "format_version": FORMAT_VERSION,
            "provenance": runtime_provenance(), "config": config or {}, **extra_meta}
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.array(json.dumps(meta, default=json_default))
    with artifact_writes():             # the .npz and its sidecar: both or neither
        out = atomic_write_bytes(path, lambda f: _write_npz(f, payload))
        save_timing(path, timing or {})   # clock readings and the machine (outside the hashed bytes)
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


def save_timing(path: str | os.PathLike, timing: dict[str, Any], artifact: str | os.PathLike | None = None) -> Path:
    """Write the timing sidecar of ``path`` (adds ``created``, the UTC time of writing, the machine, and the
    ``stamp``: the name and SHA-256 of the file it describes, ``artifact`` or ``path`` itself; a folder such
    as a training run's names its checkpoint). :func:`load_timing` ignores a sidecar whose stamp does not
    match: after ``git checkout`` + ``dvc checkout`` restores another run's artifacts, their timing files
    (not DVC outputs) still describe the run made here."""
    described = Path(artifact) if artifact is not None else Path(path)
    rec = {"created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
           **timing}
    if described.is_file():
        rec["stamp"] = {"file": portable_path(described, timing_path(path).parent),
                        "sha256": file_sha256(described)}
    data = json.dumps(rec, default=json_default, indent=1).encode()
    return atomic_write_bytes(timing_path(path), lambda f: f.write(data))


#: timing sidecars :func:`load_timing` ignored because their artifact changed since (the report says so)
IGNORED_TIMINGS: set[str] = set()


def load_timing(path: str | os.PathLike) -> dict[str, Any]:
    """The timing sidecar of ``path``; empty when it is missing, unreadable, or stamped with another
    artifact's SHA-256 than the file now there (recorded in :data:`IGNORED_TIMINGS`). Timings are
    informative, never needed to load the artifact itself; sidecars written before the stamp are read as
    they are."""
    tp = timing_path(path)
    try:
        rec = json.loads(tp.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(rec, dict):
        return {}
    stamp = rec.get("stamp")
    if stamp is not None:
        ok = isinstance(stamp, dict) and isinstance(stamp.get("file"), str)
        described = tp.parent / stamp["file"] if ok else None
        if not ok or not described.is_file() or _sha256_cached(described) != stamp.get("sha256"):
            IGNORED_TIMINGS.add(str(tp))
            return {}
    return rec


def _sha256_cached(path: Path) -> str:
    st = path.stat()
    return _sha256_of(str(path.resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=4096)
def _sha256_of(path: str, size: int, mtime_ns: int) -> str:
    return file_sha256(path)


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


#: the type of every metadata field sdp writes (:func:`save_npz` and its callers); a field of another type
#: makes the artifact corrupt (one line), never a ``TypeError`` deep in the code that reads it (each is checked
#: where present).
META_TYPES: dict[str, tuple[type, ...]] = {
    "kind": (str,), "format_version": (int,), "provenance": (dict,), "config": (dict,), "task": (str,),
    "task_options": (dict,), "task_params": (dict,), "dims": (dict,), "stats": (dict,), "source": (str,),
    "device": (str,), "method": (str,), "policy_config": (dict,), "policy_epoch": (int, type(None)),
    "policy_dataset": (dict, type(None)),
}
_TYPE_WORDS = {str: "a string", int: "an integer", dict: "a JSON object", type(None): "null"}


def _check_meta(path: Path, raw, kind: str | None) -> dict[str, Any]:
    try:
        meta = json.loads(str(raw))
    except json.JSONDecodeError as e:
        raise SdpError(f"corrupt artifact {path}: bad metadata ({e})") from None
    if not isinstance(meta, dict):
        raise SdpError(f"corrupt artifact {path}: its metadata is not a JSON object")
    for key, types in META_TYPES.items():
        v = meta.get(key)
        if key in meta and (not isinstance(v, types) or (isinstance(v, bool) and bool not in types)):
            raise SdpError(f"corrupt artifact {path}: metadata field {key!r} must be "
                           f"{' or '.join(_TYPE_WORDS[t] for t in types)}, got {v!r}"[:300])
    if kind is not None and meta.get("kind") != kind:
        raise SdpError(f"{path} is a {meta.get('kind')!r} artifact, expected {kind!r}")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise SdpError(f"{path} has format_version {meta['format_version']}, newer than this sdp "
                       f"({FORMAT_VERSION}); upgrade sdp")
    return meta

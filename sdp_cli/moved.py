"""Modules that moved into the layer folders (2026-12-06, issue "One Policy interface..."): their old import paths
keep working for one release (until 0.2), as aliases of the new modules, with a ``DeprecationWarning`` naming the
new path. ``import sdp_cli.collect`` gives the module object of ``sdp_cli.algorithm.collect`` itself, so monkey
patches and ``isinstance`` checks see one module."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: the layer folder each moved module now lives in
LAYERS = {
    "algorithm": ("argmin", "collect", "evaluate", "loop", "loop_options", "refine", "rollout", "solve_jobs"),
    "training": ("stack_optim", "train", "train_stack", "train_step"),
    "experiments": ("estimate", "experiment", "pipeline", "runner"),
    "execution": ("executor", "executor_base", "executor_dask", "interrupts", "workers"),
}
#: old import path -> new one
MOVED = {f"sdp_cli.{m}": f"sdp_cli.{layer}.{m}" for layer, mods in LAYERS.items() for m in mods}


class _Alias(importlib.abc.Loader):
    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        return None                          # a placeholder module, replaced in exec_module

    def exec_module(self, module) -> None:
        warnings.warn(f"{module.__name__} moved to {self.target}; the old path goes in sdp 0.2",
                      DeprecationWarning, stacklevel=2)
        sys.modules[module.__name__] = importlib.import_module(self.target)   # the import returns this one


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        new = MOVED.get(name)
        return importlib.util.spec_from_loader(name, _Alias(new)) if new else None


def install() -> None:
    """Make the old paths importable (once per process)."""
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())     # (before an editable install's finder, which maps old files)

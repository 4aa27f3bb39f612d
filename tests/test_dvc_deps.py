"""Every DVC stage depends on the code it runs: the modules its `sdp` subcommand imports
(transitively, inside sdp_cli) are all covered by the stage's `deps`, so no stale result survives a
code change (iterative/example-get-started's rule)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "sdp_cli"
#: what each stage's command runs (entry modules); the CLI layer, errors and progress bars are exempt
ENTRIES = {"group": ["sdp_cli.experiments.runner", "sdp_cli.algorithm.loop", "sdp_cli.algorithm.collect", "sdp_cli.training.train", "sdp_cli.algorithm.rollout",
                     "sdp_cli.algorithm.refine", "sdp_cli.algorithm.evaluate"],
           "report": ["sdp_cli.report.make"]}
EXEMPT = {"sdp_cli/__init__.py", "sdp_cli/errors.py", "sdp_cli/progress.py", "sdp_cli/cli.py", "sdp_cli/cli_options.py",
          "sdp_cli/moved.py"}   # (the old import paths: plumbing that computes nothing)


def _file(mod: str) -> Path | None:
    p = ROOT / Path(*mod.split("."))
    return p.with_suffix(".py") if p.with_suffix(".py").is_file() else (p / "__init__.py" if p.is_dir() else None)


def _closure(entries: list[str]) -> set[str]:
    seen, todo = set(), list(entries)
    while todo:
        mod = todo.pop()
        f = _file(mod)
        if f is None or mod in seen:
            continue
        seen.add(mod)
        for node in ast.walk(ast.parse(f.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            todo += [n for n in names if n.startswith("sdp_cli")]
        parts = mod.split(".")
        todo += [".".join(parts[:i]) for i in range(2, len(parts))]    # parent packages run their __init__
    return {str(_file(m).relative_to(ROOT)) for m in seen}


@pytest.mark.parametrize("stage", sorted(ENTRIES))
def test_stage_deps_cover_the_code_it_runs(stage):
    spec = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage]
    deps = (spec.get("do") or spec)["deps"]
    code = [d for d in deps if isinstance(d, str) and d.startswith("sdp_cli")]
    missing = [f for f in sorted(_closure(ENTRIES[stage]) - EXEMPT)
               if not any(f == d or f.startswith(d.rstrip("/") + "/") for d in code)]
    assert not missing, f"dvc.yaml stage {stage!r} runs {missing} but does not depend on them"


@pytest.mark.parametrize("stage", sorted(ENTRIES))
def test_stage_file_deps_are_code_it_runs(stage):
    """No stale file deps: a module the stage does not import is no reason to re-run it."""
    spec = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage]
    deps = (spec.get("do") or spec)["deps"]
    files = [d for d in deps if isinstance(d, str) and d.startswith("sdp_cli") and d.endswith(".py")]
    extra = sorted(set(files) - _closure(ENTRIES[stage]))
    assert not extra, f"dvc.yaml stage {stage!r} depends on {extra} but does not run them"

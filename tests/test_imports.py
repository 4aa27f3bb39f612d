"""The package's import graph (every `import` of an sdp_cli module, including the ones inside
functions) has no cycle: each module can be read, tested and replaced on its own (e.g. `sdp collect`
and `sdp refine` share their solve jobs through sdp_cli.algorithm.solve_jobs instead of importing each other)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _modules() -> dict[str, Path]:
    out = {}
    for f in (ROOT / "sdp_cli").rglob("*.py"):
        parts = list(f.relative_to(ROOT).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def _is_type_checking(test) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def import_graph() -> dict[str, set[str]]:
    mods = _modules()

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for m, f in mods.items():
        deps = set()
        tree = ast.parse(f.read_text())
        typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node.test)
                       for n in ast.walk(node)}
        for node in ast.walk(tree):
            if id(node) in typing_only:   # `if TYPE_CHECKING:` imports are annotations, never run
                continue
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            deps |= {owner(n) for n in names if n.startswith("sdp_cli")}
        # a package's own submodules and the packages above a module are not edges of a cycle
        graph[m] = {d for d in deps if d and d != m and not m.startswith(d + ".") and not d.startswith(m + ".")}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state and (c := visit(d)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_no_import_cycles():
    graph = import_graph()
    assert "sdp_cli.algorithm.solve_jobs" in graph["sdp_cli.algorithm.collect"] and "sdp_cli.algorithm.solve_jobs" in graph["sdp_cli.algorithm.refine"]
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The module graph collapsed to ``sdp_cli``'s first level: a sub-package (``sdp_cli.tasks``) or a module."""
    def top(m: str) -> str:
        return ".".join(m.split(".")[:2])

    out: dict[str, set[str]] = {}
    for m, deps in graph.items():
        out.setdefault(top(m), set()).update(top(d) for d in deps if top(d) != top(m))
    return out


def test_packages_have_no_import_cycle_and_tasks_import_nothing_above_them():
    """tasks/ is the domain layer: it may use the casadi transcription of Pinocchio (sdp_cli.dynamics) and the
    project's error type, nothing that uses tasks (the policies, data, rollout, solve jobs, optimizers, checks)."""
    packages = package_graph(import_graph())
    assert find_cycle(packages) is None, " -> ".join(find_cycle(packages))
    assert packages["sdp_cli.tasks"] <= {"sdp_cli.dynamics", "sdp_cli.errors"}, sorted(packages["sdp_cli.tasks"])
    assert "sdp_cli.tasks" in packages["sdp_cli.checks"]      # the check-task orchestration lives above tasks/


#: the layers of the folders, bottom up: a package may import its own layer's helpers and the layers below
LAYERS = [{"sdp_cli.errors", "sdp_cli.families", "sdp_cli.rules", "sdp_cli.seeds", "sdp_cli.kernels", "sdp_cli.execution",
           "sdp_cli.dynamics"},
          {"sdp_cli.tasks", "sdp_cli.trajopt"}, {"sdp_cli.data", "sdp_cli.losses"}, {"sdp_cli.policy"},
          {"sdp_cli.training"}, {"sdp_cli.algorithm"}, {"sdp_cli.experiments", "sdp_cli.migrate"},
          {"sdp_cli.checks", "sdp_cli.report"}]


def test_folders_are_layers_and_no_package_imports_a_layer_above_it():
    packages = package_graph(import_graph())
    level = {p: i for i, layer in enumerate(LAYERS) for p in layer}
    up = [(p, d) for p, deps in packages.items() if p in level for d in deps if level.get(d, -1) > level[p]]
    assert not up, up
    assert packages["sdp_cli.execution"] <= {"sdp_cli.errors"}, packages["sdp_cli.execution"]


def test_package_graph_sees_an_upward_import():
    graph = {"sdp_cli.tasks.base": {"sdp_cli.algorithm.rollout"}, "sdp_cli.algorithm.rollout": {"sdp_cli.tasks.base"}}
    assert package_graph(graph) == {"sdp_cli.tasks": {"sdp_cli.algorithm"}, "sdp_cli.algorithm": {"sdp_cli.tasks"}}
    assert find_cycle(package_graph(graph)) is not None


def test_the_old_paths_of_moved_modules_are_the_new_modules_for_one_release():
    import importlib
    import sys
    import warnings

    from sdp_cli.moved import MOVED

    for old, new in MOVED.items():
        assert (ROOT / Path(*new.split("."))).with_suffix(".py").is_file() and not (
            ROOT / Path(*old.split("."))).with_suffix(".py").exists(), (old, new)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sys.modules.pop("sdp_cli.collect", None)
        old = importlib.import_module("sdp_cli.collect")
    assert old is importlib.import_module("sdp_cli.algorithm.collect")
    assert any(issubclass(w.category, DeprecationWarning) and "sdp_cli.algorithm.collect" in str(w.message)
               for w in caught)


def test_the_cli_starts_without_the_lazy_dependencies():
    """``LAZY_IMPORTS`` stay out of the CLI's start-up (imported inside the functions that use them)."""
    import os
    import subprocess
    import sys

    from sdp_cli import LAZY_IMPORTS
    from sdp_cli.tasks import TASK_MODULES_ENV

    env = {k: v for k, v in os.environ.items() if k != TASK_MODULES_ENV}   # (a plugin may import anything)
    code = f"import sys, sdp_cli.cli; print(sorted(m for m in {LAZY_IMPORTS!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120,
                         env=env).stdout
    assert out.strip() == "[]", out


#: function-level imports that must run late, each with its reason (every other one is of LAZY_IMPORTS or of a
#: module of sdp that imports one of them at module level)
LATE = {("sdp_cli/__main__.py", "sdp_cli.cli"): "Ctrl-C during the CLI's start-up is caught around this import",
        ("sdp_cli/cli.py", "typer._click"): "typer's vendored click, or click: whichever this typer has",
        ("sdp_cli/cli.py", "click"): "typer's vendored click, or click: whichever this typer has",
        ("sdp_cli/policy/__init__.py", "importlib"): "the package's lazy attributes (torch on first use)",
        ("sdp_cli/policy/__init__.py", "sdp_cli.policy.api"): "the package's lazy attributes (torch on first use)",
        ("sdp_cli/trajopt/__init__.py", "sdp_cli.trajopt.ddp"): "the package would import itself back",
        ("sdp_cli/algorithm/collect.py", "sdp_cli.policy"): "load_policy is a lazy attribute: it imports torch",
        ("sdp_cli/execution/executor.py", "sdp_cli.execution.executor_dask"): "dask only for --executor dask",
        ("sdp_cli/execution/executor.py", "sdp_cli.execution.workers"): "run in the worker process it starts",
        ("sdp_cli/execution/workers.py", "ctypes"): "Linux only, inside its platform guard"}


def test_function_level_imports_are_lazy_dependencies_or_must_run_late():
    from sdp_cli import LAZY_IMPORTS

    mods = _modules()
    trees = {m: ast.parse(f.read_text()) for m, f in mods.items()}

    def owner(name):
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    def targets(node):
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        return [] if node.level else [node.module] + [f"{node.module}.{a.name}" for a in node.names]

    heavy: dict[str, bool] = {}

    def is_heavy(m, seen=()):
        if m not in heavy and m not in seen:
            parts = m.split(".")
            heavy[m] = any(t.split(".")[0] in LAZY_IMPORTS or (t.startswith("sdp_cli") and owner(t) not in (None, m)
                                                               and is_heavy(owner(t), seen + (m,)))
                           for n in trees[m].body if isinstance(n, (ast.Import, ast.ImportFrom)) for t in targets(n)) \
                or any(is_heavy(".".join(parts[:i]), seen + (m,)) for i in range(2, len(parts)) if ".".join(parts[:i]) in mods)
        return heavy.get(m, False)

    eager = []
    for m, tree in trees.items():
        rel = str(mods[m].relative_to(ROOT))
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(fn):
                    if isinstance(node, (ast.Import, ast.ImportFrom)):
                        ts = targets(node)
                        lazy = any(t.split(".")[0] in LAZY_IMPORTS or (t.startswith("sdp_cli") and owner(t) and is_heavy(owner(t)))
                                   for t in ts)
                        late = any((rel, t.rpartition(".")[0] if t.count(".") and (rel, t) not in LATE else t) in LATE
                                   or (rel, t) in LATE for t in ts)
                        if not (lazy or late):
                            eager.append(f"{rel}:{node.lineno} {ast.unparse(node)}")
    assert not eager, "hoist these to module level (or give the reason in LATE):\n" + "\n".join(eager)

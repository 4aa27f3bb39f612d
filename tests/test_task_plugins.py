"""Tasks from outside the package: a file passed with ``sdp --task-module`` (inherited by worker processes
and sub-commands through ``SDP_TASK_MODULES``) and an installed package's ``sdp.tasks`` entry point work
with every command and with the task contract checks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import sdp_cli.tasks as tasks_module
from sdp_cli.cli import app
from sdp_cli.errors import SdpError

#: a user's task module: the toy turntable task, written against sdp's Task interface only
TASK_SOURCE = (Path(__file__).parent / "toy_tasks.py").read_text()


@pytest.fixture()
def clean_registry(monkeypatch):
    """Whatever a test registers or loads is forgotten after it (and SDP_TASK_MODULES restored)."""
    monkeypatch.delenv(tasks_module.TASK_MODULES_ENV, raising=False)
    registry, loaded, modules = dict(tasks_module._REGISTRY), set(tasks_module._LOADED_FILES), set(sys.modules)
    yield
    for name in set(tasks_module._REGISTRY) - set(registry):
        tasks_module._REGISTRY.pop(name)
    tasks_module._LOADED_FILES.clear()
    tasks_module._LOADED_FILES.update(loaded)
    for m in set(sys.modules) - modules:
        if m.startswith("sdp_task_module_") or m == "spinplug":
            sys.modules.pop(m)
    tasks_module._make.cache_clear()


def _ok(r):
    assert r.exit_code == 0, r.output
    return r.output


def test_a_task_module_file_runs_collect_train_rollout_and_reaches_workers(clean_registry, tmp_path):
    f = tmp_path / "my_task.py"
    f.write_text(TASK_SOURCE + "\nfrom sdp_cli.tasks import register\n\n"
                 'register("spin", lambda **kw: TurntableTask(name="spin", **kw), "a turntable (user file)")\n')
    run = CliRunner().invoke
    out = _ok(run(app, ["--task-module", str(f), "tasks"]))
    assert "spin" in out and "a turntable (user file)" in out
    assert os.environ[tasks_module.TASK_MODULES_ENV] == str(f.resolve())
    # 2 pool workers (they inherit the registration), then train and roll out in this process
    _ok(run(app, ["--task-module", str(f), "collect", "--task", "spin", "--n-traj", "2", "--workers", "2",
                  "--out", str(tmp_path / "d.npz")]))
    _ok(run(app, ["--task-module", str(f), "train", "--data", str(tmp_path / "d.npz"), "--method", "sdp",
                  "--epochs", "2", "--horizon", "8", "--batch-size", "16", "--out", str(tmp_path / "run")]))
    # a sub-command in another process knows the task through SDP_TASK_MODULES alone
    env = dict(os.environ)
    r = subprocess.run([sys.executable, "-m", "sdp_cli.cli", "rollout", "--policy", str(tmp_path / "run"), "--n", "3",
                        "--out", str(tmp_path / "r.npz"), "--progress"], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and "sdp mean cost" in r.stdout, r.stderr
    from sdp_cli.data.artifacts import load_npz

    arrays, meta = load_npz(tmp_path / "r.npz", kind="rollout")
    assert meta["task"] == "spin" and arrays["X"].shape[:2] == (3, 41)
    # without the module the same artifacts are refused with the one-line hint
    env.pop(tasks_module.TASK_MODULES_ENV)
    r = subprocess.run([sys.executable, "-m", "sdp_cli.cli", "rollout", "--policy", str(tmp_path / "run"), "--n", "3",
                        "--out", str(tmp_path / "r2.npz")], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "--task-module FILE.py" in r.stderr, r.stderr
    assert not (tmp_path / "r2.npz").exists()


def test_an_installed_package_entry_point_is_a_task_for_every_command(clean_registry, tmp_path, monkeypatch):
    site = tmp_path / "site"
    (site / "spinplug").mkdir(parents=True)
    (site / "spinplug" / "__init__.py").write_text(TASK_SOURCE + "\n\ndef SpinTask(**options):\n"
                                                   '    return TurntableTask(name="spin-ep", **options)\n')
    info = site / "spinplug-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: spinplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text('[sdp.tasks]\nspin-ep = spinplug:SpinTask\nur5-fixed = spinplug:SpinTask\n')
    monkeypatch.syspath_prepend(str(site))
    tasks_module._load_entry_points()
    assert "spin-ep" in tasks_module.task_names() and "spinplug" not in sys.modules   # loaded when first used
    assert "ur5-fixed" in tasks_module._BUILTIN and tasks_module._REGISTRY["ur5-fixed"][1].startswith("UR5")
    task = tasks_module.get_task("spin-ep", T=30)
    assert task.name == "spin-ep" and task.T == 30
    out = _ok(CliRunner().invoke(app, ["check-task", "spin-ep", "--cases", "8:4"]))
    assert "task 'spin-ep' passes all" in out and "memorizer (T_h 8, T_a 4)" in out
    # and in a fresh process, installed packages are found at start-up
    r = subprocess.run([sys.executable, "-m", "sdp_cli.cli", "tasks"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])})
    assert r.returncode == 0 and "spin-ep" in r.stdout and "plugin spinplug" in r.stdout, r.stderr
    assert "ignoring plugin task 'ur5-fixed'" in r.stderr


def test_bad_task_modules_are_one_line_errors_and_built_in_names_are_kept(clean_registry, tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("raise ValueError('no robot here')\n")
    clash = tmp_path / "clash.py"
    clash.write_text(TASK_SOURCE + '\nfrom sdp_cli.tasks import register\n\nregister("pendulum", TurntableTask, "x")\n')
    for args, msg in ((["--task-module", str(tmp_path / "missing.py"), "tasks"], "not a Python file"),
                      (["--task-module", str(bad), "tasks"], "failed: ValueError: no robot here"),
                      (["--task-module", str(clash), "tasks"], "task 'pendulum' is built in")):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 1 and msg in r.output and "Traceback" not in r.output, r.output
    assert tasks_module.get_task("pendulum").nq == 1
    with pytest.raises(SdpError, match="pass --plugin FILE.py"):
        tasks_module.get_task("no-such-task")

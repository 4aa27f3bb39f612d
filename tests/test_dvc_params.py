"""DVC users' habits: an experiment's settings are DVC parameters of its file (groups keyed by name), so
`dvc exp run -S 'pipelines/NAME.yaml:groups.GROUP.KEY=V'` changes a setting, `dvc params diff` shows what
changed and `dvc exp show` tabulates experiments with their metrics. At 38d2c04 the knobs lived in
pipelines/NAME.yaml while params.yaml was generated, so DVC saw none of them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = """description: a tiny experiment for the DVC parameter test
groups:
  g:
    task: pendulum
    methods: [dp]
    seeds: [0]
    n_traj: [2]
    epochs: 2
    horizon: 8
    t_a: 4
    n_test: 2
    train: {batch_size: 8}
"""


def _run(cmd, cwd, env):
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    assert r.returncode == 0, " ".join(cmd) + "\n" + r.stdout[-3000:] + r.stderr[-3000:]
    return r.stdout


def test_dvc_exp_run_set_param_changes_a_group_setting(tmp_path):
    bindir = Path(sys.executable).parent
    if shutil.which("dvc", path=str(bindir)) is None:
        pytest.fail("dvc is not installed in this environment (pip install -e '.[test]')")
    work = tmp_path / "repo"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    for f in files:
        if f.startswith(("sdp_cli/", ".dvc/")) or f in ("dvc.yaml", ".dvcignore", "pyproject.toml"):
            if (ROOT / f).is_file():
                (work / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / f, work / f)
    (work / "pipelines").mkdir()
    (work / "pipelines" / "tinyexp.yaml").write_text(TINY)
    env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}", "SDP_WORKERS": "1",
           "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    _run(["git", "init", "-q"], work, env)
    _run(["sdp", "pipeline", "tinyexp"], work, env)
    _run(["git", "add", "-A"], work, env)
    _run(["git", "commit", "-qm", "tiny"], work, env)
    _run(["dvc", "repro"], work, env)
    _run(["git", "add", "-A"], work, env)
    _run(["git", "commit", "-qm", "baseline"], work, env)
    out = _run(["dvc", "exp", "run", "-S", "pipelines/tinyexp.yaml:groups.g.epochs=3"], work, env)
    assert "Ran experiment" in out
    cfg = json.loads((work / "runs" / "tinyexp" / "pendulum-dp-n2-s0" / "loop_config.json").read_text())
    assert cfg["train"]["data"]["epochs"] == 3                 # the run was made with the new setting
    assert list((work / "runs" / "superseded" / "tinyexp").iterdir())   # the old run moved aside, not deleted
    diff = _run(["dvc", "params", "diff"], work, env)
    assert "groups.g.epochs" in diff and "2" in diff and "3" in diff
    header = _run(["dvc", "exp", "show", "--no-pager", "--csv"], work, env).splitlines()[0]
    assert "groups.g.epochs" in header                         # the setting as a column
    metrics = json.loads((work / "metrics" / "tinyexp.json").read_text())
    first = next(iter(metrics))
    assert any(col.startswith(first) for col in header.split(","))   # and the experiment's metrics

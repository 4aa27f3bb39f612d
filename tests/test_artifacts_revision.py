"""The git revision recorded in artifacts: run outputs in the repository do not make it dirty."""

from __future__ import annotations

import subprocess

from sdp_cli.data.artifacts import revision_of


def _git(cwd, *args):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                   env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                        "GIT_COMMITTER_EMAIL": "t@t", "HOME": str(cwd), "PATH": "/usr/bin:/bin"})


def test_outputs_are_not_modifications_but_code_is(tmp_path):
    (tmp_path / "results").mkdir()
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "results" / "table.csv").write_text("a\n1\n")
    (tmp_path / "dvc.lock").write_text("v: 1\n")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", "-A")
    _git(tmp_path, "commit", "-q", "-m", "init")
    rev = revision_of(tmp_path)
    assert len(rev) == 40 and not rev.endswith("+dirty")
    (tmp_path / "results" / "table.csv").write_text("a\n2\n")
    (tmp_path / "dvc.lock").write_text("v: 2\n")
    assert revision_of(tmp_path) == rev
    (tmp_path / "code.py").write_text("x = 2\n")
    assert revision_of(tmp_path) == rev + "+dirty"
    assert revision_of(tmp_path / "results" / "..").endswith("+dirty")
    assert revision_of(tmp_path.parent / "not-a-repo-xyz") == "unknown"

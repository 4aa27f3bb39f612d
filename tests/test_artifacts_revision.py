"""The git revision recorded in artifacts: run outputs in the repository do not make it dirty."""

from __future__ import annotations

import subprocess

from sdp_cli.data.artifacts import code_revision_of, revision_of


def _git(cwd, *args):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                   env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                        "GIT_COMMITTER_EMAIL": "t@t", "HOME": str(cwd), "PATH": "/usr/bin:/bin"})


def _repo(root, files: dict) -> None:
    """A git repository at ``root`` with ``files`` (path: text) committed."""
    for path, text in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text)
    _git(root, "init", "-q")
    _git(root, "add", "-A")
    _git(root, "commit", "-q", "-m", "init")


def test_outputs_are_not_modifications_but_code_is(tmp_path):
    _repo(tmp_path, {"code.py": "x = 1\n", "results/table.csv": "a\n1\n", "dvc.lock": "v: 1\n"})
    rev = revision_of(tmp_path)
    assert len(rev) == 40 and not rev.endswith("+dirty")
    (tmp_path / "results" / "table.csv").write_text("a\n2\n")
    (tmp_path / "dvc.lock").write_text("v: 2\n")
    assert revision_of(tmp_path) == rev
    (tmp_path / "code.py").write_text("x = 2\n")
    assert revision_of(tmp_path) == rev + "+dirty"
    assert revision_of(tmp_path / "results" / "..").endswith("+dirty")
    assert revision_of(tmp_path.parent / "not-a-repo-xyz") == "unknown"


def test_artifacts_record_the_last_commit_of_the_code(tmp_path):
    """A commit of results or docs leaves the recorded revision (and so the artifacts' bytes) as it was;
    a commit of the code changes it; uncommitted code is +dirty."""
    _repo(tmp_path, {"sdp_cli/m.py": "x = 1\n", "README.md": "a\n"})
    rev = code_revision_of(tmp_path)
    assert len(rev) == 40
    (tmp_path / "README.md").write_text("b\n")
    _git(tmp_path, "commit", "-q", "-am", "docs")
    assert code_revision_of(tmp_path) == rev != revision_of(tmp_path)
    (tmp_path / "sdp_cli" / "m.py").write_text("x = 2\n")
    assert code_revision_of(tmp_path) == rev + "+dirty"
    _git(tmp_path, "commit", "-q", "-am", "code 2")
    assert code_revision_of(tmp_path) == revision_of(tmp_path) != rev


def test_evaluation_manifest_names_the_code_that_computed_the_rows(tmp_path, monkeypatch):
    """A loop resumed at a later commit rewrites eval.csv and its manifest; the manifest must still
    name the revision recorded in the rollouts (and the refinement, when it differs), not the
    revision of the code that re-wrote the CSV."""
    import json

    import numpy as np

    import sdp_cli.algorithm.evaluate as ev
    import sdp_cli.data.artifacts as art
    from sdp_cli.algorithm.evaluate import evaluation_artifacts, manifest_path, write_evaluation

    def at(rev):      # provenance is cached per process: patch it and the revision the manifest falls back on
        monkeypatch.setattr(art, "provenance", lambda: {"git_rev": rev})
        monkeypatch.setattr(art, "code_revision", lambda: rev)
        monkeypatch.setattr(ev, "code_revision", lambda: rev)      # (the name evaluate.py calls)

    def saved_at(rev, path, kind):
        at(rev)
        art.save_npz(path, {"X": np.zeros((2, 3))}, kind=kind)

    saved_at("a" * 40, tmp_path / "rollout.npz", "rollout")
    saved_at("a" * 40, tmp_path / "refined_same.npz", "dataset")
    saved_at("b" * 40, tmp_path / "refined_later.npz", "dataset")
    at("c" * 40)     # the code re-writing the CSV
    rows = [{"run": "r", "iteration": 0, "t_a": 4}, {"run": "r", "iteration": 0, "t_a": 8}]
    arts = [evaluation_artifacts(tmp_path / "rollout.npz", tmp_path / "refined_same.npz"),
            evaluation_artifacts(tmp_path / "rollout.npz", tmp_path / "refined_later.npz")]
    man = json.loads(manifest_path(write_evaluation(rows, tmp_path / "eval.csv", arts)).read_text())
    assert [e["git_rev"] for e in man["entries"]] == ["a" * 40, "a" * 40 + "+" + "b" * 40]
    assert "c" * 40 not in json.dumps(man)
    assert man["git_rev"] == "a" * 40 + "," + "a" * 40 + "+" + "b" * 40


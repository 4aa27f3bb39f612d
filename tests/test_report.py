"""The results/ top index written by `sdp report` next to each experiment folder."""

from __future__ import annotations

from sdp_cli.report.make import _top_index


def test_top_index_lists_each_experiment_with_its_commit(tmp_path):
    results = tmp_path / "results"
    for name, commit in (("small", "abc123"), ("fig2", "def456")):
        (results / name).mkdir(parents=True)
        (results / name / "README.md").write_text(
            f"# Results: {name}\n\nProduced by `sdp report --runs runs/{name} --out results/{name}` at commit `{commit}`\n")
        (results / name / "all_runs.csv").write_text("a\n1\n")
    (results / "stray").mkdir()  # no README: not an experiment folder
    text = _top_index(results).read_text()
    assert "| [fig2](fig2/README.md) | `def456` | 1 |" in text
    assert "| [small](small/README.md) | `abc123` | 1 |" in text
    assert "stray" not in text
    assert text.index("fig2") < text.index("small")

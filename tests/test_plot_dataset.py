"""`sdp plot-dataset`: writes a figure for UR5 / quadrotor / pendulum datasets, clean errors on bad input."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import save_npz
from sdp_cli.report.figures.plot_dataset import goal_point, trajectory_points
from sdp_cli.tasks import get_task

runner = CliRunner()


def _dataset(path, name, n=3, T=20):
    """A dataset artifact whose trajectories are the naive guesses (enough to plot)."""
    task = get_task(name, T=T)
    xis = np.array([task.sample_xi(np.random.default_rng([0, i])) for i in range(n)])
    X = np.array([task.naive_guess(xi)[0] for xi in xis])
    save_npz(path, {"X": X, "xi": xis}, kind="dataset", task=name, task_options={"T": T})
    return task, X, xis


@pytest.mark.parametrize("name", ["quadrotor-9", "ur5-rinit-rtgt", "pendulum"])
def test_plot_dataset_writes_an_image(tmp_path, name):
    src, out = tmp_path / "d.npz", tmp_path / "fig.png"
    _dataset(src, name)
    r = runner.invoke(app, ["plot-dataset", str(src), "--out", str(out), "--max-traj", "2"])
    assert r.exit_code == 0, r.output
    assert "2 trajectories" in r.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_points_are_ee_or_base_positions(tmp_path):
    task, X, xis = _dataset(tmp_path / "u.npz", "ur5-rtgt")
    P = trajectory_points(task, X[0])
    assert P.shape == (21, 3)
    np.testing.assert_allclose(P[-1], task.target(xis[0]), atol=1e-2)  # the guess ends at an IK solution
    np.testing.assert_array_equal(goal_point(task, xis[0]), task.target(xis[0]))
    task, X, xis = _dataset(tmp_path / "q.npz", "quadrotor-1")
    np.testing.assert_array_equal(trajectory_points(task, X[0]), X[0, :, :3])
    pend = get_task("pendulum")
    np.testing.assert_allclose(trajectory_points(pend, np.zeros((1, 2)))[0], pend.goal)


def test_plot_dataset_bad_input_is_one_line_error(tmp_path):
    out = tmp_path / "fig.png"
    r = runner.invoke(app, ["plot-dataset", str(tmp_path / "missing.npz"), "--out", str(out)])
    assert r.exit_code == 1 and "artifact not found" in r.output and "Traceback" not in r.output
    src = tmp_path / "d.npz"
    _dataset(src, "quadrotor-0")
    r = runner.invoke(app, ["plot-dataset", str(src), "--out", str(tmp_path / "fig.txt")])
    assert r.exit_code == 1 and "--out must end with" in r.output
    r = runner.invoke(app, ["plot-dataset", str(src), "--out", str(out), "--max-traj", "0"])
    assert r.exit_code == 1 and "--max-traj" in r.output
    save_npz(tmp_path / "r.npz", {"X": np.zeros(3)}, kind="rollouts")
    r = runner.invoke(app, ["plot-dataset", str(tmp_path / "r.npz"), "--out", str(out)])
    assert r.exit_code == 1 and "expected 'dataset'" in r.output
    assert not out.exists()

"""``sdp evaluate``'s row: the per-instance quantities it summarizes."""

from __future__ import annotations


def test_evaluation_row_counts_violations_and_goal_distance(tmp_path):
    """violation_rate: share of rollouts over the feasibility tolerance (diverged ones count);
    goal_distance_median over the finite distances."""
    import numpy as np

    from sdp_cli.data.artifacts import save_npz
    from sdp_cli.algorithm.evaluate import VIOLATION_TOL, evaluation_row

    viol = np.array([0.0, 0.5 * VIOLATION_TOL, 2 * VIOLATION_TOL, 0.3, np.inf])
    goal = np.array([0.01, 0.02, 0.5, 1.0, np.inf])
    path = save_npz(tmp_path / "rollout.npz", {"cost": np.array([1.0, 2, 3, 4, np.inf]), "max_violation": viol,
                                               "goal_distance": goal, "diverged": np.isinf(goal),
                                               "reached": goal < 0.05}, kind="rollout", config={"t_a": 4, "seed": 0},
                    policy_config={"T_h": 32, "seed": 3})
    row = evaluation_row(path)
    assert row["violation_rate"] == 3 / 5
    assert row["goal_distance_median"] == 0.5
    assert row["success_rate"] == 2 / 5 and row["diverged"] == 1
    assert row["horizon"] == 32 and row["train_seed"] == 3 and row["t_a"] == 4

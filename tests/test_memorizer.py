"""A perfect learner must score TO's cost: the memorizer (nearest training chunk) rolled out with the
rollout's own conventions on its training instances reproduces their TO cost, for every (task, T_h, T_a)
the pipelines use; and every time a rollout replans is a training start (solver-free).

At 38d2c04 (chunk starts stopped at T - T_h + 1) the memorizer scored 1479x and 2921x TO's cost on two
ur5-fixed instances at (T_h 64, T_a 63)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sdp_cli.data.chunks import ChunkDataset
from sdp_cli.tasks import get_task, task_names
from sdp_cli.policy.base import ChunkPlanning
from sdp_cli.checks.contract import (MEMORIZER_RTOL, memorizer_costs, pipeline_cases, pipeline_chunk_cases,
                                   solve_instances)

ROOT = Path(__file__).resolve().parents[1]


def replan_times(T: int, t_a: int) -> list[int]:
    """When `rollout_policy` asks for a chunk: 0, T_a, 2 T_a, .. < T."""
    return list(range(0, T, t_a))


def test_every_rollout_replanning_time_is_a_training_start():
    """For each (task T, T_h, T_a) of pipelines/*.yaml: the chunk starts cover every replanning time, and
    the rollout asks for chunks exactly at those times."""
    from sdp_cli.algorithm.rollout import RolloutConfig, rollout_policy

    triples = sorted(pipeline_chunk_cases(ROOT))
    assert len(triples) > 10
    for task_name, T_h, T_a in triples:
        T = get_task(task_name).T
        n = 2
        arrays = {"X": np.zeros((n, T + 1, 2)), "U": np.zeros((n, T, 1)), "xi": np.zeros((n, 3))}
        task = get_task("pendulum", T=T)
        arrays["X"] = np.repeat(task.initial_state(task.sample_xi(np.random.default_rng(0)))[None, None], T + 1, 1)
        arrays["X"] = np.repeat(arrays["X"], n, 0)
        ds = ChunkDataset(task, arrays, T_h, with_jacobians=False)
        starts = set(np.unique(np.arange(len(ds)) % ds.n_starts))
        assert set(replan_times(T, T_a)) <= starts, (task_name, T_h, T_a)

        class Recorder(ChunkPlanning):
            K, T_o = 1, 1

            def __init__(self):
                self.task, self.T_h, self.times, self.t = task, T_h, [], 0

            def predict_chunk(self, xis, x, u_prev, generator=None, k_rollout=None):
                self.times.append(self.t)
                self.t += T_a
                return np.zeros((len(xis), T_h, 1))

        rec = Recorder()
        rollout_policy(rec, np.stack([task.sample_xi(np.random.default_rng(0))]), RolloutConfig(n=1, t_a=T_a).validate(rec))
        assert rec.times == replan_times(T, T_a)


def _memorizer_matches(task_name, cases, n_traj=2):
    task = get_task(task_name)
    arrays = solve_instances(task, n_traj)
    to = np.array([task.cost(X, U, xi) for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"])])
    for T_h, T_a in cases:
        costs = memorizer_costs(task, arrays, T_h, T_a)
        np.testing.assert_allclose(costs, to, rtol=MEMORIZER_RTOL, err_msg=f"{task_name} (T_h {T_h}, T_a {T_a})")


@pytest.mark.parametrize("task_name", ["pendulum", "double_pendulum"])
def test_memorizer_scores_to_cost_on_the_pendulums(task_name):
    cases = pipeline_cases(task_name, ROOT)
    assert (32, 31) in cases and len(cases) >= 2
    _memorizer_matches(task_name, cases)


def test_memorizer_scores_to_cost_on_ur5_at_the_paper_and_fig3_chunks():
    """The case that failed at 38d2c04 (64, 63) and the paper's default (32, 31)."""
    _memorizer_matches("ur5-fixed", sorted({(64, 63), (32, 31), *pipeline_cases("ur5-fixed", ROOT)}))


@pytest.mark.slow
@pytest.mark.parametrize("task_name", [n for n in task_names() if n not in ("pendulum", "double_pendulum")])
def test_memorizer_scores_to_cost_on_every_heavy_task(task_name):
    _memorizer_matches(task_name, pipeline_cases(task_name, ROOT))

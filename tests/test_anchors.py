"""The reference bench against aligator's ProxDDP (bench/aligator_compare.py): without its environment it says
how to make one, in one line; with it (a slow test) the C++ transcription of our OCPs is exact and ProxDDP
solves them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench" / "aligator_compare.py"


def test_without_the_reference_environment_the_bench_says_how_to_make_it(tmp_path):
    r = subprocess.run([sys.executable, str(BENCH), "--n", "1"], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "SDP_ANCHORS_ENV": str(tmp_path / "absent")})
    assert r.returncode == 1
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "bash bench/anchors/setup.sh" in lines[0]


def _bench():
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import aligator_compare
    finally:
        sys.path.pop(0)
    return aligator_compare


@pytest.mark.slow
@pytest.mark.parametrize("name", ["double_pendulum", "ur5-rinit", "quadrotor-0"])
def test_the_transcription_into_aligator_is_exact_and_proxddp_solves_it(name, tmp_path):
    ac = _bench()
    missing = ac.anchors_missing()
    if missing:
        pytest.skip(missing)
    from sdp_cli.algorithm.rollout import evaluation_xis
    from sdp_cli.tasks import get_task

    task = get_task(name)
    ac.problem_files(task, tmp_path)
    xis = evaluation_xis(task, 2, 0)
    cost_err, x_err = ac.transcription_check(task, tmp_path, xis[0])
    assert cost_err <= ac.EXACT and x_err <= ac.EXACT
    # the transcription check can fail: a cost weight off by 1% is seen
    text = (tmp_path / "problem.txt").read_text().splitlines()
    key = {"double_pendulum": "W_GOAL ", "ur5-rinit": "W_EE ", "quadrotor-0": "W_P "}[name]
    text = [f"{key}{float(line.split()[1]) * 1.01!r}" if line.startswith(key) else line for line in text]
    (tmp_path / "problem.txt").write_text("\n".join(text) + "\n")
    assert ac.transcription_check(task, tmp_path, xis[0])[0] > 1e-6
    ac.problem_files(task, tmp_path)
    rows = ac.proxddp(task, tmp_path, xis, [task.naive_guess(xi) for xi in xis], (1e-3, 1e-2, "linear"))
    ac.judge(task, xis, rows)
    for r in rows:
        assert r["iterations"] >= 1 and np.all(np.isfinite(r["U"]))
        if r["converged"]:   # its cost, re-evaluated by ours on the rollout of its controls, is its own
            assert np.isfinite(r["cost"])
    assert any(r["converged"] for r in rows)

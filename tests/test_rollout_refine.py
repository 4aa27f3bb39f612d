"""Rollout (Algorithm 2), refine (ArgminCost) and evaluate on tiny trained pendulum policies."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from sdp_cli.cli import app
from sdp_cli.data.artifacts import load_npz
from sdp_cli.algorithm.collect import CollectConfig, collect
from sdp_cli.errors import SdpError
from sdp_cli.policy import load_policy
from sdp_cli.policy.config import TrainConfig
from sdp_cli.algorithm.refine import WIN_BASELINE, WIN_NONE, WIN_POLICY, argmin_cost, policy_outcomes, refine_instance
from sdp_cli.algorithm.rollout import RolloutConfig, instance_generators, rollout_policy, evaluation_xis
from sdp_cli.training.train import train

runner = CliRunner()
TINY = {"down_dims": [8, 16], "step_embed_dim": 16, "n_groups": 4, "mlp_hidden": [32, 32], "batch_size": 32}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A pendulum dataset and tiny SDP / PDDP policies trained for a few steps."""
    root = tmp_path_factory.mktemp("policies")
    data, _ = collect(CollectConfig(task="pendulum", n_traj=3, seed=0), root / "data.npz", workers=1)
    out = {"data": data}
    for method in ("sdp", "pddp"):
        cfg = TrainConfig.of(**{**TINY, "method": method, "epochs": 3, "horizon": 8})
        train(data, root / method, cfg, device="cpu", progress=False, log=lambda s: None)
        out[method] = root / method
    return out


def test_t_a_and_k_rollout_are_validated(trained):
    pol = load_policy(trained["sdp"])
    assert RolloutConfig(n=2).validate(pol).t_a == pol.T_h - pol.T_o
    with pytest.raises(SdpError, match="t_a must be in"):
        RolloutConfig(n=2, t_a=pol.T_h).validate(pol)
    with pytest.raises(SdpError, match="t_a must be an integer >= 1, got 0"):   # its own range, before any policy
        RolloutConfig(n=2, t_a=0)
    with pytest.raises(SdpError, match="k_rollout"):
        RolloutConfig(n=2, k_rollout=pol.K + 1).validate(pol)
    r = runner.invoke(app, ["rollout", "--policy", str(trained["sdp"]), "--out", "x.npz", "--t-a", "99"])
    assert r.exit_code == 1 and "t_a must be in" in r.output


def test_every_family_plans_through_one_api(trained):
    """plan() is the one action API: a chunked policy's rows after the history (n = max_t_a = T_h - T_o), a
    per-step one's control (n = max_t_a = 1, actions u); an option the family cannot honour is refused in one
    line instead of being ignored (`--t-a 5` or `--k-rollout 2` on an MLP)."""
    sdp, pddp = load_policy(trained["sdp"]), load_policy(trained["pddp"])
    xi = evaluation_xis(sdp.task, 3, 0)
    u_prev = np.zeros((3, 1))
    chunk = sdp.predict_chunk(xi, xi, u_prev, generator=instance_generators(0, range(3)))
    planned = sdp.plan(xi, xi, u_prev, generator=instance_generators(0, range(3)))
    assert sdp.max_t_a == sdp.T_h - sdp.T_o and planned.shape == (3, sdp.max_t_a, 1)
    np.testing.assert_array_equal(planned, chunk[:, sdp.T_o:])
    assert pddp.max_t_a == 1 and pddp.task.action == "u"
    np.testing.assert_array_equal(pddp.plan(xi, xi, u_prev), pddp.act(xi, xi)[:, None])
    assert RolloutConfig(n=2).validate(pddp) == RolloutConfig(n=2, t_a=1, k_rollout=None, conversion=None)
    for flags, msg in ((["--t-a", "5"], "t_a must be in [1, 1]"), (["--k-rollout", "2"], "has no sampler")):
        r = runner.invoke(app, ["rollout", "--policy", str(trained["pddp"]), "--out", "x.npz", *flags])
        assert r.exit_code == 1 and msg in r.output, r.output


def test_inpainting_keeps_the_history(trained):
    pol = load_policy(trained["sdp"])
    xi = evaluation_xis(pol.task, 4, 0)
    u_prev = np.array([[1.5], [-2.0], [0.0], [7.0]])
    tau = pol.predict_chunk(xi, xi, u_prev, generator=instance_generators(0, range(4)))
    assert tau.shape == (4, pol.T_h, 1)
    np.testing.assert_allclose(tau[:, 0], u_prev, atol=1e-4)  # torque control: a_hist = u_{t-1}


def test_batched_and_one_by_one_rollouts_agree(trained):
    pol = load_policy(trained["sdp"])
    cfg = RolloutConfig(n=3, seed=5, t_a=4).validate(pol)
    xis = evaluation_xis(pol.task, 3, 5)
    with torch.no_grad():
        batch = rollout_policy(pol, xis, cfg, generators=instance_generators(5, range(3)))
        for i in range(3):
            one = rollout_policy(pol, xis[i:i + 1], cfg, generators=instance_generators(5, [i]))
            np.testing.assert_allclose(one["U"][0], batch["U"][i], atol=1e-3)
            np.testing.assert_allclose(one["X"][0], batch["X"][i], atol=1e-3)
    # the rollout obeys the task dynamics and the control bounds
    X, U = batch["X"][0], batch["U"][0]
    task = pol.task
    assert np.all(np.abs(U) <= task.u_ub + 1e-12)
    np.testing.assert_allclose(X[5], task.step(X[4], U[4]), atol=1e-9)


def _cand(cost, converged):
    return SimpleNamespace(cost=cost, converged=converged)


def test_argmin_cost_keeps_the_cheapest_converged_candidate():
    assert argmin_cost([_cand(5.0, True), _cand(3.0, True)]) == 1
    assert argmin_cost([_cand(5.0, True), _cand(1.0, False)]) == 0   # non-converged never kept
    assert argmin_cost([None, _cand(2.0, True)]) == 1
    assert argmin_cost([_cand(1.0, False), None]) is None
    assert argmin_cost([_cand(float("nan"), True), _cand(9.0, True)]) == 1
    # the same optimum reached from both guesses differs by rounding: a tie, won by the policy guess
    assert argmin_cost([_cand(31.25, True), _cand(31.25 - 1e-13, True)]) == 0
    assert argmin_cost([_cand(31.25 - 1e-13, True), _cand(31.25, True)]) == 0
    assert argmin_cost([_cand(31.25, True), _cand(31.2, True)]) == 1


def test_policy_outcomes_count_a_shared_optimum_as_a_tie_not_a_win():
    nan = float("nan")
    winner = np.array([WIN_POLICY, WIN_POLICY, WIN_POLICY, WIN_POLICY, WIN_BASELINE, WIN_NONE])
    pol = np.array([31.25, 30.0, 12.0, 12.0, 40.0, nan])
    base = np.array([31.25 + 1e-13, 31.0, nan, 15.0, 35.0, nan])
    base_ok = np.array([True, True, False, False, True, False])
    # a shared optimum (rounding apart) is a tie; cheaper, or TO alone failed: a win; the rest neither
    assert policy_outcomes(winner, pol, base, base_ok) == (3, 1)
    # every instance a shared optimum, as on quadrotor-0 from DP (49 of 50): no win at all
    same = np.full(5, 2.5)
    assert policy_outcomes(np.full(5, WIN_POLICY), same, same * (1 + 1e-12), np.ones(5, bool)) == (0, 5)
    # the kept winner and the count agree: ArgminCost keeps the policy's solve exactly on wins and ties
    for i in range(len(pol)):
        cands = [SimpleNamespace(cost=pol[i], converged=winner[i] == WIN_POLICY or np.isfinite(pol[i])),
                 SimpleNamespace(cost=base[i], converged=bool(base_ok[i]))]
        kept = argmin_cost(cands)
        assert (kept == 0) == (winner[i] == WIN_POLICY)


def test_refine_instance_never_keeps_a_non_converged_solve(trained):
    from sdp_cli.tasks import get_task

    task = get_task("pendulum")
    xi = evaluation_xis(task, 1, 0)[0]
    X0, U0 = task.naive_guess(xi)
    rec = refine_instance("pendulum", {}, xi, X0, U0, max_iter=1, baseline=True)
    assert rec["winner"] == WIN_NONE and not bool(rec["converged"])
    rec = refine_instance("pendulum", {}, xi, X0, U0, max_iter=1000, baseline=True)
    assert rec["winner"] in (WIN_POLICY, WIN_BASELINE) and bool(rec["converged"])
    best = min(c for c, ok in ((rec["pol_cost"], rec["pol_converged"]), (rec["base_cost"], rec["base_converged"])) if ok)
    assert float(rec["cost"]) == pytest.approx(best)


@pytest.mark.parametrize("method", ["sdp", "pddp"])
def test_rollout_refine_evaluate_cli(trained, tmp_path, method):
    ro, rf, ev = tmp_path / "r.npz", tmp_path / "f.npz", tmp_path / "e.csv"
    r = runner.invoke(app, ["rollout", "--policy", str(trained[method]), "--task", "pendulum", "--n", "3",
                            "--seed", "1", "--out", str(ro)])
    assert r.exit_code == 0, r.output
    a, meta = load_npz(ro, kind="rollout")
    assert a["X"].shape == (3, 101, 2) and a["cost"].shape == (3,) and meta["method"] == method
    # the policy is recorded relative to the rollout's folder and resolves from there
    assert not Path(meta["config"]["policy"]).is_absolute()
    assert (ro.parent / meta["config"]["policy"]).resolve() == Path(trained[method]).resolve()
    r = runner.invoke(app, ["refine", "--rollouts", str(ro), "--out", str(rf), "--workers", "1"])
    assert r.exit_code == 0, r.output
    d, dmeta = load_npz(rf, kind="dataset")
    assert d["K"].shape[1:] == (100, 1, 2) and len(d["inst_winner"]) == 3   # a training dataset
    assert np.all(d["cost"] <= np.where(d["inst_base_converged"][d["index"]], d["inst_base_cost"][d["index"]], np.inf) + 1e-9)
    # both solutions are kept for the plots; the kept one is the winner's
    assert d["inst_pol_X"].shape == d["inst_base_X"].shape == (3, 101, 2)
    for k, i in enumerate(d["index"]):
        src = d["inst_pol_X"] if d["inst_winner"][i] == 0 else d["inst_base_X"]
        np.testing.assert_array_equal(src[i], d["X"][k])
    r = runner.invoke(app, ["evaluate", "--rollouts", str(ro), "--refined", str(rf), "--out", str(ev),
                            "--tag", "experiment=t"])
    assert r.exit_code == 0, r.output
    row = pd.read_csv(ev).iloc[0]
    assert row["method"] == method and row["n"] == 3 and row["experiment"] == "t"
    # the paper's "refined" is the solve from the policy guess alone, not ArgminCost with TO alone
    pol_ok = d["inst_pol_converged"].astype(bool)
    if pol_ok.any():
        assert row["refined_cost_mean"] == pytest.approx(float(np.mean(d["inst_pol_cost"][pol_ok])))
    assert row["refined_converged_rate"] == pytest.approx(float(np.mean(pol_ok)))
    best = np.where(d["inst_winner"] == 0, d["inst_pol_cost"], d["inst_base_cost"])[d["inst_winner"] >= 0]
    assert row["argmin_cost_mean"] == pytest.approx(float(np.mean(best)))
    assert row["policy_wins"] + row["policy_ties"] == int(np.sum(d["inst_winner"] == 0))
    r = runner.invoke(app, ["rollout", "--policy", str(trained[method]), "--task", "double_pendulum",
                            "--out", str(tmp_path / "z.npz")])
    assert r.exit_code == 1 and "trained on task 'pendulum'" in r.output


def test_a_diverged_finite_rollout_is_no_warm_start():
    """A DP rollout of the fig2 run (old double pendulum, cost 3e14, states up to 1.6e7, all finite):
    fatrop never returned from this guess (its line search looped for > 25 min), so refine must
    not start the solver from it, and TO alone still gives the instance a converged solution.
    On the faithful double pendulum its cost is small (the costs do not see velocities): the state
    bound DIVERGENCE_STATE rejects it."""
    from pathlib import Path

    from sdp_cli.algorithm.refine import usable_guess
    from sdp_cli.tasks import get_task

    g = np.load(Path(__file__).parent / "data" / "diverged_double_pendulum_guess.npz")
    task = get_task("double_pendulum")
    assert np.all(np.isfinite(g["X"])) and not usable_guess(task, g["xi"], g["X"], g["U"])
    rec = refine_instance("double_pendulum", {}, g["xi"], g["X"], g["U"], max_iter=1000, baseline=True)
    assert rec["pol_iterations"] == -1 and rec["winner"] == WIN_BASELINE and bool(rec["converged"])
    # the TO solution itself is a usable guess; NaN states are not
    X, U = rec["X"], rec["U"]
    assert usable_guess(task, g["xi"], X, U)
    X_nan = X.copy()
    X_nan[50:] = np.nan
    assert not usable_guess(task, g["xi"], X_nan, U)


def test_single_shooting_baseline_is_reported_from_both_guesses(trained, tmp_path):
    """`sdp refine --single-shooting`: the second TO-alone baseline (controls only, states by rollout,
    IPOPT) from the naive and the policy controls; its solutions are feasible optima of the task and are
    reported, never kept in the dataset."""
    from sdp_cli.tasks import get_task
    from sdp_cli.trajopt.single_shooting import get_single_shooting

    task = get_task("pendulum")
    xi = evaluation_xis(task, 1, 3)[0]
    res = get_single_shooting(task).solve(xi, task.naive_guess(xi)[1])
    assert res.converged and res.iterations > 0 and res.max_violation <= 1e-6
    assert res.cost == pytest.approx(task.cost(res.X, res.U, xi), rel=1e-9)      # the rollout of its controls
    np.testing.assert_allclose(res.X, task.simulate(task.initial_state(xi), res.U), atol=1e-9)
    ro, rf, ev = tmp_path / "r.npz", tmp_path / "f.npz", tmp_path / "e.csv"
    assert runner.invoke(app, ["rollout", "--policy", str(trained["sdp"]), "--n", "2", "--out", str(ro)]).exit_code == 0
    r = runner.invoke(app, ["refine", "--rollouts", str(ro), "--out", str(rf), "--workers", "1", "--single-shooting"])
    assert r.exit_code == 0, r.output
    d, meta = load_npz(rf, kind="dataset")
    assert meta["config"]["single_shooting"] and d["inst_ss_base_converged"].all()
    assert runner.invoke(app, ["evaluate", "--rollouts", str(ro), "--refined", str(rf), "--out", str(ev)]).exit_code == 0
    row = pd.read_csv(ev).iloc[0]
    assert row["ss_to_alone_converged_rate"] == 1.0
    assert row["ss_to_alone_cost_mean"] == pytest.approx(float(np.mean(d["inst_ss_base_cost"])))
    assert "ss_refined_cost_mean" in row


def test_a_rollout_names_its_policy_from_its_folder_and_older_ones_from_where_they_ran(tmp_path, monkeypatch):
    from sdp_cli.algorithm.evaluate import _recorded_policy

    (tmp_path / "runs" / "policy").mkdir(parents=True)
    (tmp_path / "runs" / "eval").mkdir()
    monkeypatch.chdir(tmp_path)
    want = (tmp_path / "runs" / "policy").resolve()
    assert _recorded_policy("../policy", tmp_path / "runs" / "eval").resolve() == want       # this code's record
    assert _recorded_policy("runs/policy", tmp_path / "runs" / "eval").resolve() == want     # older: cwd-relative
    assert _recorded_policy(str(want), tmp_path / "runs" / "eval") == want                   # older: absolute
    assert _recorded_policy(None, tmp_path) is None

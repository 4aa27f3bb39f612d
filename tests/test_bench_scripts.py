"""What the bench scripts print and keep: ties are not wins (bench/refine.py), the solver cache is bounded
(bench/trajopt.py's gain check grew it to 17.5 GB at 38d2c04)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench(name):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_refine_bench_does_not_count_ties_as_wins():
    # instance 0: policy kept, TO alone equal (tie); 1: policy kept and cheaper (win); 2: TO alone kept;
    # 3: policy kept, TO alone failed (win)
    d = {"inst_winner": np.array([0, 0, 1, 0]), "inst_pol_cost": np.array([1.0, 1.0, 3.0, 2.0]),
         "inst_base_cost": np.array([1.0, 1.5, 2.0, np.inf]),
         "inst_base_converged": np.array([True, True, True, False])}
    assert "won 2/4" in _bench("refine").outcome_line(d, 4) and "tied 1" in _bench("refine").outcome_line(d, 4)


def test_solver_cache_is_bounded():
    from sdp_cli.tasks import get_task
    from sdp_cli.trajopt import solver as S

    task = get_task("pendulum", T=12)
    first = S.get_solver(task, horizon=2, jit=False)
    for h in range(3, 3 + S.SOLVER_CACHE_SIZE + 4):      # one per re-solved horizon, as the gain check does
        S.get_solver(task, horizon=h, jit=False)
    assert len(S._CACHE[task]) == S.SOLVER_CACHE_SIZE
    assert S.get_solver(task, horizon=3 + S.SOLVER_CACHE_SIZE + 3, jit=False) is S.get_solver(
        task, horizon=3 + S.SOLVER_CACHE_SIZE + 3, jit=False)         # still a cache
    assert S.get_solver(task, horizon=2, jit=False) is not first       # the oldest was dropped


def test_trainer_bench_compares_with_the_optimisation_of_38d2c04_and_puts_the_trainers_back():
    """bench/stacked_train.py --trainer times the solo step of 38d2c04 (foreach AdamW, per-tensor EMA) beside the
    trainer's (fused AdamW, foreach EMA), and leaves the trainer's in place afterwards."""
    import torch

    import sdp_cli.training.train as tr
    from sdp_cli.policy.config import TrainConfig

    cfg, params = TrainConfig.of(method="dp"), [torch.nn.Parameter(torch.zeros(3))]
    before = (tr.optimizer_for, tr.ema_for)
    with _bench("stacked_train")._solo_38d2c04():
        opt, ema = tr.optimizer_for(cfg, params), tr.ema_for(cfg, params)
        assert opt.defaults["foreach"] and not opt.defaults["fused"] and not ema.foreach
    assert (tr.optimizer_for, tr.ema_for) == before
    opt, ema = tr.optimizer_for(cfg, params), tr.ema_for(cfg, params)
    assert opt.defaults["fused"] and ema.foreach


def test_packing_bench_keeps_the_rule_it_compares_with():
    """bench/stack_packing.py's "across sizes" rule is the packing until 2026-11-27: sorted by dataset size (the
    experiment's order within a size), cut every --stack, so n_traj 8 of seed 2 shared a stack with n_traj 32."""
    from types import SimpleNamespace

    runs = {f"n{n}-s{s}": SimpleNamespace(n_traj_at=lambda k, n=n: n) for n in (32, 2, 16, 4, 8) for s in (0, 1, 2)}
    jobs = _bench("stack_packing").across_sizes(list(runs), runs, 8)
    assert jobs == [["n2-s0", "n2-s1", "n2-s2", "n4-s0", "n4-s1", "n4-s2", "n8-s0", "n8-s1"],
                    ["n8-s2", "n16-s0", "n16-s1", "n16-s2", "n32-s0", "n32-s1", "n32-s2"]]


def test_action_noise_bench_perturbs_only_the_played_rows_in_the_networks_units():
    """bench/action_noise.py: the inpainted history rows stay exact, noise is sigma x the coordinate's half-range,
    an offset is one draw held over a chunk, and the blocks of a state action partition it."""
    from sdp_cli.policy.memorizer import NoisyMemorizer

    mod = _bench("action_noise")

    class Base:
        task, T_h, T_o = None, 6, 1

        def predict_chunk(self, xis, x, u_prev, generator=None, k_rollout=None):
            return np.ones((len(xis), 6, 3))

    scale = np.array([1.0, 10.0, 0.0])
    xis = np.zeros((4000, 1))
    white = NoisyMemorizer(Base(), scale, 0.01, "white", seed=0).predict_chunk(xis, None, None)
    assert np.all(white[:, 0] == 1.0) and np.all(white[:, :, 2] == 1.0)
    assert np.allclose((white[:, 1:, :2] - 1).std(axis=(0, 1)), [0.01, 0.1], rtol=0.05)
    offset = NoisyMemorizer(Base(), scale, 0.01, "offset", seed=0).predict_chunk(xis, None, None)
    assert np.all(offset[:, 0] == 1.0) and np.allclose(offset[:, 1:], offset[:, 1:2])
    assert np.all(NoisyMemorizer(Base(), scale, 0.0, "white", seed=0).predict_chunk(xis, None, None) == 1.0)
    b = mod.blocks(12, 6)
    assert [np.arange(12)[s].tolist() for s in b.values()] == [list(range(6)), [6, 7, 8], [9, 10, 11]]


def test_conversion_confirmation_reads_back_the_per_run_rows_it_wrote():
    """``--keep-missing`` keeps the rows of runs whose folders are gone: the "Per run" table it wrote reads back
    as the same rows (to the 3 significant digits it prints), NaNs included."""
    import pandas as pd

    mod = _bench("conversion_confirmation")
    df = pd.DataFrame({"run": ["quadrotor-0-dp-n2-s0", "quadrotor-9-sdp-n30-s0"], "task": ["quadrotor-0", "quadrotor-9"],
                       "T_a": [31, 16], "method": ["dp", "sdp"],
                       "n_traj": [2, 100], "seed": [0, 0], "conversion": ["tracking", "inverse-dynamics"],
                       "instances": ["train (2)", "test (50)"], "success": [0.5, 0.0],
                       "final distance median (m)": [0.0412, 3.52], "policy cost median": [0.842, 693.0],
                       "cost / TO median": [1.33, float("nan")]})
    page = lambda d: "\n".join(["# x", "", "## Per run", "", d.to_markdown(index=False, floatfmt=".3g"), "",  # noqa: E731
                                mod.MARKER, "", "## Per run", "", "| run |", "|---|", "| old |"])
    back = mod.per_run_table(page(df))
    assert list(back.columns) == list(df.columns) and len(back) == 2      # the earlier confirmations are not read
    pd.testing.assert_frame_equal(back.reset_index(drop=True), df, check_dtype=False)
    assert mod.per_run_table("# nothing here").empty
    # a page written before the task and T_a columns (fig1's quadrotor-0 runs at the default T_a 31) reads back with them
    old = mod.per_run_table(page(df.iloc[:1].drop(columns=["task", "T_a"])))
    pd.testing.assert_frame_equal(old, df.iloc[:1], check_dtype=False)


def test_conversion_confirmation_rolls_out_the_last_finished_iteration_with_the_data_it_trained_on(tmp_path):
    """A loop with --keep-buffer trains iteration k > 0 on it<k>/buffer.npz (sdp_cli.algorithm.loop.iteration_data):
    the bench must read that, not it<k>/data.npz (the last collection alone); an iteration whose training did not
    finish (it3 here) is not the run's final policy; a run with no finished iteration is refused."""
    from sdp_cli.policy.checkpoint import save_checkpoint

    mod = _bench("conversion_confirmation")
    run = tmp_path / "quadrotor-9-sdp-n30-s0"
    for k, finished, buffer in [(0, True, False), (1, True, True), (2, True, True), (3, False, True), (10, False, False)]:
        save_checkpoint(run / f"it{k}" / "policy" / "checkpoint.pt", {"finished": finished})
        (run / f"it{k}" / "data.npz").write_bytes(b"")
        if buffer:
            (run / f"it{k}" / "buffer.npz").write_bytes(b"")
    assert mod.final_iteration(run) == (run / "it2", run / "it2" / "buffer.npz")   # it2, not it10 (by number)
    (run / "it2" / "buffer.npz").unlink()                                          # a --reset-buffer loop
    assert mod.final_iteration(run) == (run / "it2", run / "it2" / "data.npz")
    save_checkpoint(run / "it10" / "policy" / "checkpoint.pt", {"finished": True})
    assert mod.final_iteration(run)[0] == run / "it10"                             # numeric order, not text
    empty = tmp_path / "empty"
    save_checkpoint(empty / "it0" / "policy" / "checkpoint.pt", {"finished": False})
    with pytest.raises(SystemExit, match="no iteration has finished"):
        mod.final_iteration(empty)


def test_conversion_confirmation_selects_finished_runs_by_prefix_and_method(tmp_path):
    """``--prefix quadrotor-`` (every layout of fig4) selects by the method part of the run name, wherever it sits
    after the prefix (at 82's first fig4 call it compared the layout's digit with the methods and found nothing)."""
    mod = _bench("conversion_confirmation")
    names = ["quadrotor-0-sdp-n50-s0", "quadrotor-1-dp-n50-s0", "quadrotor-9-sdp-n30-s0-ddp", "quadrotor-3-mlp-n50-s0",
             "ur5-fixed-sdp-n8-s0", "quadrotor-3-sdp-n50-s0"]
    for n in names:
        (tmp_path / n).mkdir()
        if n != "quadrotor-3-sdp-n50-s0":           # still running: no summary.csv
            (tmp_path / n / "summary.csv").write_text("x\n")
    got = [p.name for p in mod.selected_runs(tmp_path, "quadrotor-", ["sdp", "dp"])]
    assert got == ["quadrotor-0-sdp-n50-s0", "quadrotor-1-dp-n50-s0", "quadrotor-9-sdp-n30-s0-ddp"]
    assert [p.name for p in mod.selected_runs(tmp_path, "quadrotor-0-", ["dp"])] == []


def test_chunk_consistency_is_zero_along_the_dynamics_and_sees_a_jump_in_position():
    from sdp_cli.tasks import get_task

    task = get_task("quadrotor-0")
    rng = np.random.default_rng(0)
    xi = task.sample_xi(rng)
    U = task.u_hover + rng.uniform(-0.3, 0.3, (12, task.nu))          # a tumbling, accelerating flight
    X = task.simulate(task.initial_state(xi), U)                        # (13, nx)
    mm = _bench("chunk_consistency").row_mismatch
    along = mm(task, X[None])
    assert along.shape == (1, len(X) - 1) and np.max(along) < 1e-9
    bad = X.copy()
    bad[5, 2] += 0.01                                                   # row 5 one centimetre higher
    jump = mm(task, bad[None])[0]
    assert jump[4] == pytest.approx(1.0, rel=1e-6) and jump[5] == pytest.approx(1.0, rel=1e-6)
    assert np.max(np.delete(jump, [4, 5])) < 1e-9

"""``sdp refine``: trajectory optimization warm-started by a policy (Algorithm 1, line 7).

For every instance of a rollout artifact, the OCP is solved from the policy's (X, U)
and, unless disabled, from the naive ``Interpolate`` guess; :func:`argmin_cost` keeps
the converged candidate with the lowest cost. The output is a ``dataset`` artifact of
the same format as ``sdp collect`` (the kept, converged trajectories with gains) plus
per-instance records over *all* instances (``inst_*`` arrays, see docs/artifacts.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from sdp_cli.data.artifacts import file_sha256, load_npz, save_npz, split_timing
from sdp_cli.data.collect import RESULT_KEYS
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.base import check_task_params

#: winner codes stored in ``inst_winner``
WIN_NONE, WIN_POLICY, WIN_BASELINE = -1, 0, 1
#: relative cost difference under which two converged solves tie in ArgminCost
TIE_RTOL = 1e-9


def argmin_cost(candidates: Sequence) -> int | None:
    """Index of the converged candidate with the lowest cost; None if none converged.

    ``candidates`` are objects with ``converged`` and ``cost`` (e.g. ``SolveResult``);
    ``None`` entries (candidates that were not computed) are skipped. Costs within
    ``TIE_RTOL`` of each other are a tie, won by the earlier candidate (the policy guess):
    two solves that reach the same optimum differ by rounding (1e-13), which must not decide.
    """
    best, best_cost = None, np.inf
    for i, c in enumerate(candidates):
        if c is None or not bool(c.converged) or not np.isfinite(c.cost):
            continue
        if c.cost < best_cost - TIE_RTOL * max(1.0, abs(best_cost) if np.isfinite(best_cost) else 0.0):
            best, best_cost = i, float(c.cost)
    return best


def usable_guess(task, xi: np.ndarray, X: np.ndarray, U: np.ndarray) -> bool:
    """A policy rollout worth warm-starting from: finite, not diverged (states within
    ``DIVERGENCE_STATE``, cost <= ``DIVERGENCE_COST``)."""
    from sdp_cli.rollout import DIVERGENCE_COST, DIVERGENCE_STATE

    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(U))) or np.abs(X).max() > DIVERGENCE_STATE:
        return False
    with np.errstate(all="ignore"):
        cost = task.cost(X, U, xi)
    return bool(np.isfinite(cost) and cost <= DIVERGENCE_COST)


#: per-instance single-shooting fields and their values when that solve was not run
SS_MISSING = {"cost": np.nan, "iterations": -1, "converged": False, "time": 0.0}
SS_KEYS = tuple(f"ss_{g}_{k}" for g in ("pol", "base") for k in SS_MISSING)


def _single_shooting_record(task, xi, U_pol, usable: bool, baseline: bool, max_iter: int) -> dict:
    """The second TO baseline (:mod:`sdp_cli.trajopt.single_shooting`) from the policy's and the naive controls."""
    from sdp_cli.trajopt.single_shooting import get_single_shooting

    ss = get_single_shooting(task, max_iter)
    rec = {}
    for g, guess in (("pol", U_pol if usable else None), ("base", task.naive_guess(xi)[1] if baseline else None)):
        if guess is None:
            rec.update({f"ss_{g}_{k}": v for k, v in SS_MISSING.items()})
            continue
        r = ss.solve(xi, guess)
        rec.update({f"ss_{g}_cost": r.cost, f"ss_{g}_iterations": r.iterations,
                    f"ss_{g}_converged": bool(r.converged), f"ss_{g}_time": r.solve_time})
    return rec


def refine_instance(task_name: str, task_options: dict, xi: np.ndarray, X_pol: np.ndarray,
                    U_pol: np.ndarray, max_iter: int, baseline: bool, single_shooting: bool = False) -> dict:
    """Solve one instance from the policy guess (and the naive guess); picklable dict out.

    ``single_shooting``: also solve both with the single-shooting baseline (``ss_*`` records; reported,
    never kept in the dataset)."""
    from sdp_cli.trajopt import get_solver

    task = get_task(task_name, **task_options)
    solver = get_solver(task, max_iter=max_iter)
    U_pol = np.clip(U_pol, task.u_lb, task.u_ub)
    # a diverged rollout (non-finite, or cost above the rollout's divergence threshold) is no
    # guess: solving from states of 1e7 wastes the iteration budget at best, and fatrop's line
    # search can loop forever from there
    usable = usable_guess(task, xi, X_pol, U_pol)
    pol = solver.solve(xi, X_pol, U_pol) if usable else None
    base = solver.solve(xi, *task.naive_guess(xi)) if baseline else None
    win = argmin_cost([pol, base])
    rec = {
        "xi": xi,
        "pol_cost": pol.cost if pol else np.nan, "pol_iterations": pol.iterations if pol else -1,
        "pol_converged": bool(pol.converged) if pol else False, "pol_time": pol.solve_time if pol else 0.0,
        "base_cost": base.cost if base else np.nan, "base_iterations": base.iterations if base else -1,
        "base_converged": bool(base.converged) if base else False, "base_time": base.solve_time if base else 0.0,
        "winner": WIN_NONE if win is None else (WIN_POLICY if win == 0 else WIN_BASELINE),
        # both solutions, for plots (TO alone vs refined); NaN where not solved
        "pol_X": pol.X if pol else np.full(X_pol.shape, np.nan),
        "base_X": base.X if base else np.full(X_pol.shape, np.nan),
    }
    # the kept candidate, or (for the record) whichever was computed; never kept unless converged
    res = (pol, base)[win] if win is not None else (pol if pol is not None else base)
    if res is not None:
        rec.update({k: np.asarray(getattr(res, k)) for k in RESULT_KEYS})
    rec["converged"] = np.asarray(win is not None)
    if single_shooting:
        rec.update(_single_shooting_record(task, xi, U_pol, usable, baseline, max_iter))
    return rec


@dataclass
class RefineStats:
    n: int = 0
    kept: int = 0
    policy_wins: int = 0
    mean_pol_iterations: float = float("nan")
    mean_base_iterations: float = float("nan")
    mean_pol_time: float = float("nan")
    mean_base_time: float = float("nan")


def failed_record(xi: np.ndarray, status: str) -> dict:
    """The record of an instance whose job raised: nothing converged, nothing kept."""
    return {"xi": xi, "pol_cost": np.nan, "pol_iterations": -1, "pol_converged": False, "pol_time": 0.0,
            "base_cost": np.nan, "base_iterations": -1, "base_converged": False, "base_time": 0.0,
            "winner": WIN_NONE, "converged": np.asarray(False), "status": status, "pol_X": None, "base_X": None,
            **{f"ss_{g}_{k}": v for g in ("pol", "base") for k, v in SS_MISSING.items()}}


def refine(rollouts: str | os.PathLike, out: str | os.PathLike, max_iter: int = 1000,
           baseline: bool = True, single_shooting: bool = False, workers: int | None = None,
           progress: Callable[[int], None] | None = None, executor: "str | Executor" = "local",
           scheduler: str | None = None) -> tuple[Path, RefineStats]:
    """Refine every rollout of an artifact; write a dataset artifact to ``out``.

    ``progress(done, n)`` is called after each instance. ``executor``/``workers``/``scheduler``: where the solves run, as for ``sdp collect``
    (:func:`sdp_cli.executor.make_executor`, or an open executor, not closed here). A job
    that raises counts as an instance where nothing converged.
    """
    from sdp_cli.data.collect import warm_solver
    from sdp_cli.executor import Executor, check_executor_options, error_status, make_executor

    arrays, meta = load_npz(rollouts, kind="rollout")
    for k in ("X", "U", "xi"):
        if k not in arrays:
            raise SdpError(f"corrupt rollout artifact {rollouts}: missing {k}")
    if max_iter <= 0:
        raise SdpError(f"max_iter must be > 0, got {max_iter}")
    if not meta.get("task"):
        raise SdpError(f"corrupt rollout artifact {rollouts}: no task name in its metadata")
    task_name, task_options = meta["task"], meta.get("task_options", {})
    task = get_task(task_name, **task_options)
    check_task_params(task, meta.get("task_params"), f"rollout artifact {rollouts}")
    n = len(arrays["xi"])
    own = not isinstance(executor, Executor)
    if own and not scheduler:
        workers = max(1, min(workers or os.cpu_count() or 1, n))
    if own:
        check_executor_options(executor, workers, scheduler)
    recs: list[dict | None] = [None] * n
    ex = make_executor(executor, workers, scheduler) if own else executor
    try:
        described = ex.describe()
        ex.warm(warm_solver, task_name, task_options, max_iter)  # once per worker process
        argsets = [(task_name, task_options, arrays["xi"][i], arrays["X"][i], arrays["U"][i], max_iter, baseline,
                    single_shooting) for i in range(n)]
        for i, res in ex.imap_unordered(refine_instance, argsets):
            recs[i] = res.value if res.ok else failed_record(arrays["xi"][i], error_status(res.error))
            if progress:
                progress(sum(r is not None for r in recs), n)
    finally:
        if own:
            ex.close()
    kept = [i for i in range(n) if recs[i]["winner"] != WIN_NONE]
    out_arrays = {f"inst_{k}": np.array([r[k] for r in recs]) for k in
                  ("pol_cost", "pol_iterations", "pol_converged", "pol_time", "base_cost",
                   "base_iterations", "base_converged", "base_time", "winner")}
    if single_shooting:
        out_arrays.update({f"inst_{k}": np.array([r[k] for r in recs]) for k in SS_KEYS})
    out_arrays["inst_xi"] = arrays["xi"]
    nan_X = np.full(arrays["X"].shape[1:], np.nan)
    for k in ("pol_X", "base_X"):  # (n, T+1, nx): the solve from the policy guess / naive guess
        out_arrays[f"inst_{k}"] = np.stack([nan_X if r[k] is None else np.asarray(r[k]) for r in recs])
    for k in RESULT_KEYS:
        shape = np.asarray(recs[kept[0]][k]).shape if kept else ()
        out_arrays[k] = np.stack([recs[i][k] for i in kept]) if kept else np.zeros((0, *shape))
    out_arrays["xi"] = arrays["xi"][kept]
    out_arrays["index"] = np.asarray(kept, dtype=int)
    out_arrays["converged"] = np.ones(len(kept), dtype=bool)
    w = out_arrays["inst_winner"]
    stats = RefineStats(
        n=n, kept=len(kept), policy_wins=int(np.sum(w == WIN_POLICY)),
        mean_pol_iterations=float(np.mean(out_arrays["inst_pol_iterations"])),
        mean_base_iterations=float(np.mean(out_arrays["inst_base_iterations"])) if baseline else float("nan"),
        mean_pol_time=float(np.mean(out_arrays["inst_pol_time"])),
        mean_base_time=float(np.mean(out_arrays["inst_base_time"])) if baseline else float("nan"))
    dims = task.dims()
    out_arrays, timing = split_timing(out_arrays)   # clock readings go to the timing sidecar
    meta_stats, stats_timing = split_timing(stats.__dict__)
    path = save_npz(out, out_arrays, kind="dataset",
                    config={"rollouts": str(rollouts), "rollouts_sha256": file_sha256(rollouts),
                            "max_iter": max_iter, "baseline": baseline, "single_shooting": single_shooting,
                            "workers": described.get("workers"),
                            "executor": described, "rollout_config": meta.get("config", {})},
                    task=task_name, task_params=task.params(), task_options=task_options, dims=dims,
                    source="refine", stats=meta_stats, timing={**timing, **stats_timing})
    return path, stats

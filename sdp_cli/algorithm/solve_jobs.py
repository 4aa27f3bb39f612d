"""The per-instance solve jobs of Algorithm 1 (lines 5-8), shared by ``sdp collect`` and ``sdp refine``.

Each job is a module-level function of small, picklable arguments that returns a dict of
arrays, so that any executor (:mod:`sdp_cli.execution.executor`) can run it: :func:`solve_index`
(TO from the naive guess, line 5), :func:`refine_instance` (TO from the policy's rollout and
from the naive guess, kept by :func:`argmin_cost`, lines 6-8), :func:`refine_indices` (the same for several
instances, labelled with their sample indices, for ``sdp collect --policy``), and :func:`solve_indices` /
:func:`refine_instances` for several instances in one job (one batch with the DDP). ``sdp collect`` and ``sdp refine``
both import this module and not each other.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.families import DEFAULT_TO
from sdp_cli.algorithm.argmin import TIE_RTOL, WIN_BASELINE, WIN_NONE, WIN_POLICY, argmin_cost, policy_outcomes  # noqa: F401
from sdp_cli.tasks import Task, get_task
from sdp_cli.trajopt import build_count, get_to_solver
from sdp_cli.trajopt.single_shooting import get_single_shooting

RESULT_KEYS = ("X", "U", "K", "A", "B", "Phi", "cost", "iterations", "solve_time", "converged",
               "max_violation")


def sample_xi(task: Task, seed: int, index: int) -> np.ndarray:
    """``xi_i``: a pure function of ``(seed, index)``."""
    return task.sample_xi(np.random.default_rng([int(seed), int(index)]))


def solve_index(task_name: str, task_options: dict, seed: int, index: int, max_iter: int, to: str = DEFAULT_TO) -> dict:
    """Solve instance ``index`` from the naive guess with TO family ``to``; a dict of arrays (picklable)."""
    return solve_indices(task_name, task_options, seed, [index], max_iter, to)[0]


def _solve_record(res, xi: np.ndarray, index: int) -> dict:
    out = {k: np.asarray(getattr(res, k)) for k in RESULT_KEYS}
    out["xi"] = xi
    out["index"] = np.asarray(index)
    out["status"] = np.asarray(str(res.status))
    return out


#: instances per executor job with ``to="ddp"``: solved as one batch (box-FDDP amortizes its Python overhead
#: over the batch; an instance's result does not depend on its batch, so the chunking changes no number)
DDP_BATCH = 16


def job_size(to: str) -> int:
    """Instances per executor job for TO family ``to``."""
    return DDP_BATCH if to == "ddp" else 1


def job_chunks(items: list, to: str) -> list[list]:
    """``items`` cut into the consecutive groups that one job each solves (:func:`job_size`)."""
    size = job_size(to)
    return [items[j:j + size] for j in range(0, len(items), size)]


def solve_indices(task_name: str, task_options: dict, seed: int, indices: list[int], max_iter: int,
                  to: str = DEFAULT_TO) -> list[dict]:
    """:func:`solve_index` of several indices in one job; with ``to="ddp"`` one DDP batch."""
    task = get_task(task_name, **task_options)
    solver = get_to_solver(task, to, max_iter=max_iter)
    xis = [sample_xi(task, seed, i) for i in indices]
    results = _solve_many(task, solver, to, [(xi, *task.naive_guess(xi)) for xi in xis])
    return [_solve_record(r, xi, i) for r, xi, i in zip(results, xis, indices)]


def warm_solver(task_name: str, task_options: dict, max_iter: int, to: str = DEFAULT_TO) -> int:
    """Build (or reuse) this process's solver of the task; the process's build count (NLP solvers)."""
    get_to_solver(get_task(task_name, **task_options), to, max_iter=max_iter)
    return build_count()


def failed_result(task: Task, index: int, xi: np.ndarray, status: str) -> dict:
    """The record of an attempt whose job raised: not converged, NaN arrays of the right shapes."""
    T, nx, nu, ndx = task.T, task.nx, task.nu, task.ndx
    nan = lambda *shape: np.full(shape, np.nan)
    return {"X": nan(T + 1, nx), "U": nan(T, nu), "K": nan(T, nu, ndx), "A": nan(T, ndx, ndx),
            "B": nan(T, ndx, nu), "Phi": nan(T, ndx, ndx), "cost": np.asarray(np.nan),
            "iterations": np.asarray(-1), "solve_time": np.asarray(0.0), "converged": np.asarray(False),
            "max_violation": np.asarray(np.nan), "xi": np.asarray(xi), "index": np.asarray(index),
            "status": np.asarray(status)}


def usable_guess(task, xi: np.ndarray, X: np.ndarray, U: np.ndarray) -> bool:
    """A policy rollout worth warm-starting from: finite, not diverged (states within
    ``DIVERGENCE_STATE``, cost <= ``DIVERGENCE_COST``)."""
    from sdp_cli.algorithm.rollout import DIVERGENCE_COST, DIVERGENCE_STATE

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
                    U_pol: np.ndarray, max_iter: int, baseline: bool, single_shooting: bool = False,
                    to: str = DEFAULT_TO) -> dict:
    """Solve one instance from the policy guess (and the naive guess) with TO family ``to``; picklable dict out.

    ``single_shooting``: also solve both with the single-shooting baseline (``ss_*`` records; reported,
    never kept in the dataset)."""
    return refine_instances(task_name, task_options, [xi], [X_pol], [U_pol], max_iter, baseline, single_shooting,
                            to)[0]


def refine_instances(task_name: str, task_options: dict, xis, X_pols, U_pols, max_iter: int, baseline: bool,
                     single_shooting: bool = False, to: str = DEFAULT_TO) -> list[dict]:
    """:func:`refine_instance` of several instances in one job; with ``to="ddp"`` the policy guesses are solved as
    one DDP batch and the naive guesses as another (the same results as one by one)."""
    task = get_task(task_name, **task_options)
    solver = get_to_solver(task, to, max_iter=max_iter)
    U_pols = [np.clip(U, task.u_lb, task.u_ub) for U in U_pols]
    # a diverged rollout (non-finite, or cost above the rollout's divergence threshold) is no
    # guess: solving from states of 1e7 wastes the iteration budget at best, and fatrop's line
    # search can loop forever from there
    usable = [usable_guess(task, xi, X, U) for xi, X, U in zip(xis, X_pols, U_pols)]
    pols = _solve_many(task, solver, to, [(xi, X, U) for xi, X, U, ok in zip(xis, X_pols, U_pols, usable) if ok])
    pols = iter(pols)
    pol_results = [next(pols) if ok else None for ok in usable]
    bases = _solve_many(task, solver, to, [(xi, *task.naive_guess(xi)) for xi in xis]) if baseline else [None] * len(xis)
    return [_refine_record(task, xi, X_pol, U_pol, ok, pol, base, max_iter, baseline, single_shooting)
            for xi, X_pol, U_pol, ok, pol, base in zip(xis, X_pols, U_pols, usable, pol_results, bases)]


def _solve_many(task, solver, to: str, problems: list[tuple]) -> list:
    """``solver.solve(xi, X, U)`` of each problem; one batch for the DDP."""
    if not problems:
        return []
    if to == "ddp":
        xis = np.stack([p[0] for p in problems])
        return solver.solve_batch(np.stack([task.initial_state(x) for x in xis]), xis,
                                  np.stack([p[1] for p in problems]), np.stack([p[2] for p in problems]))
    return [solver.solve(*p) for p in problems]


def _refine_record(task, xi, X_pol, U_pol, usable: bool, pol, base, max_iter: int, baseline: bool,
                   single_shooting: bool) -> dict:
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


def refine_indices(task_name, task_options, indices, xis, X_pols, U_pols, max_iter, to: str = DEFAULT_TO) -> list[dict]:
    """:func:`refine_instances` labelled with their sample indices (``sdp collect --policy``); one DDP batch with
    ``to="ddp"``."""
    recs = refine_instances(task_name, task_options, xis, X_pols, U_pols, max_iter, baseline=True, to=to)
    out = []
    for i, rec in zip(indices, recs):
        rec["index"] = np.asarray(i)
        out.append({k: np.asarray(v) for k, v in rec.items()})
    return out


def failed_record(xi: np.ndarray, status: str) -> dict:
    """The record of an instance whose job raised: nothing converged, nothing kept."""
    return {"xi": xi, "pol_cost": np.nan, "pol_iterations": -1, "pol_converged": False, "pol_time": 0.0,
            "base_cost": np.nan, "base_iterations": -1, "base_converged": False, "base_time": 0.0,
            "winner": WIN_NONE, "converged": np.asarray(False), "status": status, "pol_X": None, "base_X": None,
            **{f"ss_{g}_{k}": v for g in ("pol", "base") for k, v in SS_MISSING.items()}}


#: per-instance fields of a policy-warm-started solve, stored as ``inst_<field>`` (docs/artifacts.md)
INSTANCE_FIELDS = ("pol_cost", "pol_iterations", "pol_converged", "pol_time", "base_cost", "base_iterations",
                   "base_converged", "base_time", "winner")
_INSTANCE_MISSING = {"pol_cost": np.nan, "pol_iterations": -1, "pol_converged": False, "pol_time": 0.0,
                     "base_cost": np.nan, "base_iterations": -1, "base_converged": False, "base_time": 0.0,
                     "winner": WIN_NONE}


def instance_arrays(recs: list[dict], x_shape: tuple, single_shooting: bool = False) -> dict:
    """The ``inst_*`` arrays of policy-warm-started solves, one row per instance tried, kept or not,
    the one schema of ``sdp refine`` and ``sdp collect --policy``: ``inst_xi``, ``inst_<field>`` for
    :data:`INSTANCE_FIELDS` (and the ``ss_*`` ones with ``single_shooting``), ``inst_pol_X`` /
    ``inst_base_X`` ``(n, T+1, nx)`` (NaN where not solved). Records of jobs that raised lack fields:
    they read as not solved."""
    keys = INSTANCE_FIELDS + (SS_KEYS if single_shooting else ())
    missing = {**_INSTANCE_MISSING, **{f"ss_{g}_{k}": v for g in ("pol", "base") for k, v in SS_MISSING.items()}}
    out = {f"inst_{k}": np.array([np.asarray(r.get(k, missing[k])).item() for r in recs]) for k in keys}
    out["inst_xi"] = np.stack([np.asarray(r["xi"], dtype=float) for r in recs])
    nan_X = np.full(x_shape, np.nan)
    for k in ("pol_X", "base_X"):
        out[f"inst_{k}"] = np.stack([nan_X if r.get(k) is None or np.asarray(r.get(k)).shape != x_shape
                                     else np.asarray(r[k], dtype=float) for r in recs])
    return out

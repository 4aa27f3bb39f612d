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
from typing import Callable

import numpy as np

from sdp_cli.families import DEFAULT_TO
from sdp_cli.algorithm.argmin import (TIE_RTOL, WIN_BASELINE, WIN_NONE, WIN_POLICY, argmin_cost,  # noqa: F401 (re-exported)
                            policy_outcomes)
from sdp_cli.data.artifacts import file_sha256, load_npz, save_npz, split_timing
from sdp_cli.algorithm.solve_jobs import (RESULT_KEYS, SS_KEYS, failed_record, instance_arrays, job_chunks,  # noqa: F401
                                refine_instance, refine_instances, usable_guess, warm_solver)
from sdp_cli.errors import SdpError
from sdp_cli.tasks import get_task
from sdp_cli.tasks.base import check_task_params
from sdp_cli.execution.executor import Executor, check_executor_options, error_status, make_executor
from sdp_cli.data.artifacts import check_writable
from sdp_cli.trajopt import check_to


@dataclass
class RefineStats:
    n: int = 0
    kept: int = 0
    policy_wins: int = 0
    policy_ties: int = 0
    mean_pol_iterations: float = float("nan")
    mean_base_iterations: float = float("nan")
    mean_pol_time: float = float("nan")
    mean_base_time: float = float("nan")


def refine(rollouts: str | os.PathLike, out: str | os.PathLike, max_iter: int = 1000,
           baseline: bool = True, single_shooting: bool = False, workers: int | None = None,
           progress: Callable[[int], None] | None = None, executor: "str | Executor" = "local",
           scheduler: str | None = None, to: str = DEFAULT_TO) -> tuple[Path, RefineStats]:
    """Refine every rollout of an artifact; write a dataset artifact to ``out``.

    ``progress(done, n)`` is called after each instance. ``executor``/``workers``/``scheduler``: where the solves run, as for ``sdp collect``
    (:func:`sdp_cli.execution.executor.make_executor`, or an open executor, not closed here). A job
    that raises counts as an instance where nothing converged.
    """
    arrays, meta = load_npz(rollouts, kind="rollout")
    for k in ("X", "U", "xi"):
        if k not in arrays:
            raise SdpError(f"corrupt rollout artifact {rollouts}: missing {k}")
    if max_iter <= 0:
        raise SdpError(f"max_iter must be > 0, got {max_iter}")
    if not meta.get("task"):
        raise SdpError(f"corrupt rollout artifact {rollouts}: no task name in its metadata")

    check_writable(out)                    # before the solves, not after them
    task_name, task_options = meta["task"], meta.get("task_options", {})
    task = get_task(task_name, **task_options)
    check_task_params(task, meta.get("task_params"), f"rollout artifact {rollouts}")

    check_to(to)
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
        ex.warm(warm_solver, task_name, task_options, max_iter, to)  # once per worker process
        # one instance per job, or (--to ddp) batches solved together (the same results, amortized)
        chunks = job_chunks(list(range(n)), to)
        argsets = [(task_name, task_options, [arrays["xi"][i] for i in ch], [arrays["X"][i] for i in ch],
                    [arrays["U"][i] for i in ch], max_iter, baseline, single_shooting, to) for ch in chunks]
        for c, res in ex.imap_unordered(refine_instances, argsets):
            for i, rec in zip(chunks[c], res.value if res.ok else [None] * len(chunks[c])):
                recs[i] = rec if res.ok else failed_record(arrays["xi"][i], error_status(res.error))
            if progress:
                progress(sum(r is not None for r in recs), n)
    finally:
        if own:
            ex.close()
    kept = [i for i in range(n) if recs[i]["winner"] != WIN_NONE]
    out_arrays = instance_arrays(recs, arrays["X"].shape[1:], single_shooting)
    for k in RESULT_KEYS:
        shape = np.asarray(recs[kept[0]][k]).shape if kept else ()
        out_arrays[k] = np.stack([recs[i][k] for i in kept]) if kept else np.zeros((0, *shape))
    out_arrays["xi"] = arrays["xi"][kept]
    out_arrays["index"] = np.asarray(kept, dtype=int)
    out_arrays["converged"] = np.ones(len(kept), dtype=bool)
    wins, ties = policy_outcomes(out_arrays["inst_winner"], out_arrays["inst_pol_cost"], out_arrays["inst_base_cost"],
                                 out_arrays["inst_base_converged"])
    stats = RefineStats(
        n=n, kept=len(kept), policy_wins=wins, policy_ties=ties,
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
                            "to": to, "workers": described.get("workers"),
                            "executor": described, "rollout_config": meta.get("config", {})},
                    task=task_name, task_params=task.params(), task_options=task_options, dims=dims,
                    source="refine", stats=meta_stats, timing={**timing, **stats_timing})
    return path, stats

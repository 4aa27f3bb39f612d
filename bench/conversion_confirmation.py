"""The confirmation of the conversions: a report's quadrotor runs rolled out under each conversion from the same
checkpoints, on the test set and on their own training instances. Writes results/tasks/confirmation.md.

The runs are an experiment's own (fig1's: one iteration, 2e4 epochs, T_h 32, the default T_a 31; fig4's: T_a 16,
quadrotor-9 over 5 iterations). Each run's final policy (EMA weights of its last finished iteration, with the
dataset it was trained on: the loop's buffer under `--keep-buffer`) is rolled out at the run's own loop T_a (its
loop_config.json) with the rollout's conventions (sdp_cli.algorithm.rollout.rollout_policy, instance generators of
seed 0) under `inverse-dynamics` and `tracking`
(sdp_cli/tasks/conversion.py): on the 50 test instances of test seed 0 (the loop's own evaluation set; the row of
the run's own conversion must equal its eval.csv) and on the run's own training instances, where the memorizer
reaches TO's cost.

    python bench/conversion_confirmation.py --runs runs/fig1 --prefix quadrotor-0- [--keep-missing]

The file keeps what lies below its line `<!-- earlier confirmations -->` (the confirmations of earlier results
versions, which the ledger cites); everything above it is this bench's. With ``--keep-missing`` the per-run rows
of the file's "Per run" table whose run is not in ``--runs`` stay (as `sdp report --keep-missing` keeps the
report's earlier rows: run folders that are gone keep their measured rows), and the summary is taken over all.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

MARKER = "<!-- earlier confirmations -->"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/fig1"))
    ap.add_argument("--prefix", default="quadrotor-0-", help="run folders whose name starts with this")
    ap.add_argument("--methods", default="sdp,dp")
    ap.add_argument("--n-test", type=int, default=50)
    ap.add_argument("--out", type=Path, default=Path("results/tasks/confirmation.md"))
    ap.add_argument("--keep-missing", action="store_true",
                    help="keep the per-run rows of --out whose run folder is not in --runs")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from sdp_cli.data.artifacts import code_revision
    from sdp_cli.algorithm.rollout import (RolloutConfig, evaluate_rollouts, evaluation_xis, instance_generators,
                                 rollout_policy)
    from sdp_cli.tasks.conversion import CONVERSIONS

    methods = a.methods.split(",")
    runs = selected_runs(a.runs, a.prefix, methods)
    if not runs:
        raise SystemExit(f"no finished run (with summary.csv) in {a.runs} named {a.prefix}* with a method in {methods}")
    rows, t0 = [], time.perf_counter()
    for run in runs:
        pol, data, t_a = final_policy(run)
        task = pol.task
        to = np.array([task.cost(X, U, xi) for X, U, xi in zip(data["X"], data["U"], data["xi"])])
        sets = {f"train ({len(data['xi'])})": data["xi"], f"test ({a.n_test})": evaluation_xis(task, a.n_test, 0)}
        for conv in CONVERSIONS:
            for where, xis in sets.items():
                cfg = RolloutConfig(n=len(xis), seed=0, t_a=t_a, conversion=conv).validate(pol)
                with torch.no_grad():
                    ro = rollout_policy(pol, xis, cfg, generators=instance_generators(0, range(len(xis))))
                ev = evaluate_rollouts(task, ro["X"], ro["U"], xis)
                rows.append({"run": run.name, "task": pol.task_name, "T_a": cfg.t_a, "method": pol.method,
                             "n_traj": len(data["xi"]),
                             "seed": pol.config.seed, "conversion": conv, "instances": where,
                             "success": float(np.mean(ev["reached"])),
                             "final distance median (m)": float(np.median(ev["goal_distance"])),
                             "policy cost median": float(np.median(ev["cost"])),
                             "cost / TO median": (float(np.median(ev["cost"] / to)) if where.startswith("train")
                                                  else float("nan"))})
                print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    kept = 0
    if a.keep_missing and a.out.is_file():
        old = per_run_table(a.out.read_text())
        old = old[~old.run.isin(set(df.run))] if len(old) else old
        kept = old.run.nunique() if len(old) else 0
        df = pd.concat([old, df], ignore_index=True)
    df = df.sort_values(["task", "method", "n_traj", "seed", "conversion", "instances"])[
        ["run", "task", "T_a", *[c for c in df.columns if c not in ("run", "task", "T_a")]]]
    summary = (df.groupby(["task", "T_a", "method", "n_traj", "conversion", "instances"], sort=True)
                 .agg(runs=("run", "count"), success=("success", "mean"),
                      final_distance_median=("final distance median (m)", "median"))
                 .reset_index().rename(columns={"final_distance_median": "final distance, median of runs (m)"}))
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = ["# Confirmation: the quadrotor policies under both conversions (bench/conversion_confirmation.py)", "",
            f"Written by `python bench/conversion_confirmation.py --runs {a.runs} --prefix {a.prefix} --methods "
            f"{a.methods}` on {stamp}, code revision `{code_revision()}`, {platform.node()} ({platform.machine()}), "
            f"{time.perf_counter() - t0:.0f} s"
            + (f"; the rows of {kept} runs not in `--runs` are kept from the file's earlier version (`--keep-missing`)."
               if kept else "."), "",
            "Runs: the experiment's own, each final policy (its last iteration) rolled out at its loop's T_a "
            "from the same checkpoint under each conversion of predicted chunks (sdp_cli/tasks/conversion.py) on "
            "its own training instances and on the 50 test instances of test seed 0. Success: final distance within "
            "the task's tolerance (5 cm). Cost / TO: on the training instances, the rollout's cost over TO's on the "
            "same instance.", "",
            "## Success per task, T_a, method, n_traj, conversion and instance set (mean over runs)", "",
            summary.to_markdown(index=False, floatfmt=".3g"), "",
            "## Per run", "", df.to_markdown(index=False, floatfmt=".3g"), ""]
    earlier = ""
    if a.out.is_file():
        old = a.out.read_text()
        earlier = old.split(MARKER, 1)[1] if MARKER in old else "\n" + old
    if earlier.strip():
        text.insert(text.index("## Success per task, T_a, method, n_traj, conversion and instance set (mean over runs)"),
                    "The earlier confirmations (of earlier runs or results versions) are below the line at the end.\n")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(text) + "\n" + MARKER + "\n\n" + earlier.lstrip("\n"))
    print(f"wrote {a.out}")


def selected_runs(folder: Path, prefix: str, methods: list[str]) -> list[Path]:
    """The finished runs (``summary.csv`` written) in ``folder`` whose name starts with ``prefix`` and has one of
    ``methods`` as a dash-separated part (``quadrotor-9-sdp-n30-s0-ddp``: task, method, size, seed, tag)."""
    return sorted(p for p in folder.iterdir() if p.name.startswith(prefix) and (p / "summary.csv").is_file()
                  and set(p.name.split("-")) & set(methods))


def final_iteration(run: Path) -> tuple[Path, Path]:
    """The run's last iteration whose training finished (``it<k>``) and the dataset that training read: the
    loop's buffer (``it<k>/buffer.npz``, the union of every collection so far, which a loop with ``--keep-buffer``
    trains iteration k > 0 on: sdp_cli.algorithm.loop.iteration_data) where the loop made one, else the
    iteration's own collection (``it<k>/data.npz``)."""
    from sdp_cli.algorithm.loop import train_done

    its = sorted((p.parent for p in run.glob("it*/policy") if p.parent.name[2:].isdigit()),
                 key=lambda p: int(p.name[2:]), reverse=True)
    last = next((it for it in its if train_done(it / "policy")), None)   # newest first: one checkpoint read
    if last is None:
        raise SystemExit(f"{run}: no iteration has finished training")
    buffer = last / "buffer.npz"
    return last, buffer if buffer.is_file() else last / "data.npz"


def final_policy(run: Path):
    """The run's final policy (:func:`final_iteration`'s), the dataset it trained on and the run's loop T_a
    (its loop_config.json): ``(policy, dataset arrays, t_a)``."""
    from sdp_cli.algorithm.loop import migrate_loop_dict
    from sdp_cli.data.artifacts import load_npz
    from sdp_cli.policy import load_policy

    last, trained_on = final_iteration(run)
    data, _ = load_npz(trained_on, kind="dataset")
    t_a = migrate_loop_dict(json.loads((run / "loop_config.json").read_text()))["rollout"].get("t_a")
    return load_policy(last / "policy"), data, t_a


def per_run_table(text: str) -> pd.DataFrame:
    """The "## Per run" markdown table of an earlier output as a frame (numbers as floats, n_traj and seed as ints)."""
    lines = text.split("## Per run", 1)[1].split(MARKER, 1)[0].splitlines() if "## Per run" in text else []
    table = [ln for ln in lines if ln.startswith("|")]
    if len(table) < 3:
        return pd.DataFrame()
    cells = [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in table]
    df = pd.DataFrame(cells[2:], columns=cells[0])
    for c in df.columns:
        if c not in ("run", "task", "method", "conversion", "instances"):
            df[c] = df[c].astype(float)
    if "task" not in df:      # written before the column: fig1's quadrotor-0 runs, at the default T_a 31 of T_h 32
        df.insert(1, "task", df.run.str.rsplit(pat="-", n=3).str[0])
        df.insert(2, "T_a", 31)
    return df.astype({"n_traj": int, "seed": int, "T_a": int})


if __name__ == "__main__":
    main()

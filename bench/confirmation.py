"""Confirmation runs of results version 2: SDP and DP on ur5-fixed and quadrotor-0 after the chunk padding and
the task redefinitions, beside the committed fig1 rows. Writes results/tasks/confirmation.md.

The runs are plain `sdp loop`s (one iteration, n_traj 8, seed 0, 1e4 epochs, T_h 32, the default T_a 31,
50 test instances, no refinement), made in a folder outside the clone, e.g.

    for t in ur5-fixed quadrotor-0; do for m in sdp dp; do
      sdp loop --task $t --method $m --n-traj 8 --epochs 10000 --horizon 32 --n-test 50 --no-eval-refine \\
               --workers 1 --seed 0 --out /work/confirm/$t-$m; done; done
    python bench/confirmation.py --runs /work/confirm

Each policy is also rolled out on its own 8 training instances (the same T_a): a perfect learner
reproduces TO there (tests/test_memorizer.py). Costs are not comparable across task definitions (the
UR5 and quadrotor costs changed); success (the task's goal tolerance, 5 cm) and the median final distance
are.
"""

from __future__ import annotations

import argparse
import datetime
import platform
from pathlib import Path

import numpy as np
import pandas as pd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("results/tasks/confirmation.md"))
    ap.add_argument("--fig1", type=Path, default=Path("results/fig1/all_runs.csv"))
    ap.add_argument("--t-a-sweep", default="31,16,8,4,1", help="T_a values replayed on the training instances")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from sdp_cli.data.artifacts import code_revision, load_npz
    from sdp_cli.policy import load_policy
    from sdp_cli.algorithm.rollout import RolloutConfig, evaluate_rollouts, instance_generators, rollout_policy

    rows, sweep = [], []
    for run in sorted(p for p in a.runs.iterdir() if (p / "summary.csv").is_file()):
        data, _ = load_npz(run / "it0" / "data.npz", kind="dataset")
        pol = load_policy(run / "it0" / "policy")
        cfg = RolloutConfig(n=len(data["xi"]), seed=0).validate(pol)
        with torch.no_grad():
            ro = rollout_policy(pol, data["xi"], cfg, generators=instance_generators(0, range(len(data["xi"]))))
        ev = evaluate_rollouts(pol.task, ro["X"], ro["U"], data["xi"])
        to = np.array([pol.task.cost(X, U, xi) for X, U, xi in zip(data["X"], data["U"], data["xi"])])
        for t_a in [int(v) for v in a.t_a_sweep.split(",") if v]:
            c = RolloutConfig(n=len(data["xi"]), seed=0, t_a=t_a).validate(pol)
            with torch.no_grad():
                r = rollout_policy(pol, data["xi"], c, generators=instance_generators(0, range(len(data["xi"]))))
            e = evaluate_rollouts(pol.task, r["X"], r["U"], data["xi"])
            sweep.append({"task": pol.task_name, "method": pol.method, "T_a": t_a, "success": float(np.mean(e["reached"])),
                          "final distance median (m)": float(np.median(e["goal_distance"])),
                          "policy cost median": float(np.median(e["cost"]))})
        test, _ = load_npz(next((run / "it0" / "eval").glob("rollout_ta*.npz")), kind="rollout")
        for split, e, extra in (("train (8)", ev, {"TO cost mean": float(to.mean())}), ("test (50)", test, {})):
            rows.append({"task": pol.task_name, "method": pol.method, "instances": split,
                         "success": float(np.mean(e["reached"])),
                         "final distance median (m)": float(np.median(e["goal_distance"])),
                         "policy cost mean": float(np.mean(e["cost"])),
                         "policy cost median": float(np.median(e["cost"])), **extra, "T_h/T_a": f"{pol.T_h}/{cfg.t_a}"})
    new = pd.DataFrame(rows)
    old = pd.read_csv(a.fig1)
    old = old[old.task.isin(new.task.unique()) & old.method.isin(["sdp", "dp"]) & (old.n_traj == 8)
              & (old.train_seed == 0) & (old.epochs == 10000)]
    old = pd.DataFrame({"task": old.task, "method": old.method, "instances": "test (50)",
                        "success": old.success_rate, "final distance median (m)": old.goal_distance_median,
                        "T_h/T_a": [f"{h:g}/{t:g}" for h, t in zip(old.horizon, old.t_a)]})
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = ["# Confirmation runs on the corrected code (results version 2)", "",
            f"Written by `python bench/confirmation.py --runs {a.runs}` on {stamp}, code revision "
            f"`{code_revision()}`, {platform.node()} ({platform.machine()}).", "",
            "SDP and DP, one `sdp loop` iteration each: n_traj 8 (collection seed 0), seed 0, 1e4 epochs, T_h 32, "
            "T_a 31, 50 test instances (test seed 0), evaluated on the test set and on the policy's own 8 training "
            "instances. Success: the final goal distance within the task's tolerance (5 cm). One seed: a "
            "check that the corrections let a learned policy reach the goal, not a result of the paper's grid.", "",
            "## Results version 2 (chunks cover the episode end; UR5 and quadrotor redefined)", "",
            new.to_markdown(index=False, floatfmt=".3g"), "",
            "## The same policies replayed on their 8 training instances at other T_a (replanning more often)", "",
            pd.DataFrame(sweep).to_markdown(index=False, floatfmt=".3g"), "",
            "## The committed fig1 rows (results version 1: same n_traj, seed and epochs; UR5 at T_h 64 / T_a 63)", "",
            "Costs are not comparable across task definitions and are left out.", "",
            old.to_markdown(index=False, floatfmt=".3g"), ""]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()

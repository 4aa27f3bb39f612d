"""Training time of an experiment's stacks under two packing rules, measured side by side in one run.

    python bench/stack_packing.py [--experiment fig1] [--seeds 0,1,2] [--tasks ur5-fixed] [--methods sdp,dp]
                                  [--stack 8] [--max-s 3]

``sdp pipeline --run`` trains compatible one-iteration runs as stacks (``sdp_cli.experiments.runner.pack``); a stack pads
every member's batch to its largest. Rule "across sizes" (the packing until 2026-11-27): a training config's
runs sorted by dataset size and cut into stacks of ``--stack``, so one stack may hold n_traj 2 and 32. Rule
"one size" (``pack`` now): one dataset size per stack, split evenly. For each rule and each stack, the seconds
of one stacked step (``sdp_cli.experiments.estimate.job_step_seconds``: the trainer's own step on synthetic batches of
the task's shapes, padded to the stack's largest batch; ``step_seconds`` for a stack of one) times the steps of
its longest member; the sums per (task, method) and their ratio are printed. Every distinct (R, B) is measured
once, so both rules' sums come from the same measurements.
"""

from __future__ import annotations

import argparse

import torch


def across_sizes(names: list[str], runs: dict, stack: int) -> list[list[str]]:
    """The packing rule before 2026-11-27: by dataset size, then in the experiment's order, cut every ``stack``."""
    names = sorted(names, key=lambda n: runs[n].n_traj_at(0))
    return [names[i:i + stack] for i in range(0, len(names), stack)]


def shape(jobs, st) -> str:
    """Stacks as ``RxB``: R runs, batches padded to B (the largest batch ``st[name].B`` of the stack)."""
    return "+".join(f"{len(j)}x{max(st[n].B for n in j)}" for j in jobs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiment", default="fig1")
    ap.add_argument("--seeds", default="0,1,2", help="train seeds of the runs packed (a pipeline --only)")
    ap.add_argument("--tasks", default="ur5-fixed")
    ap.add_argument("--methods", default="sdp,dp")
    ap.add_argument("--stack", type=int, default=8)
    ap.add_argument("--max-s", type=float, default=3.0, help="seconds of measurement per (R, B)")
    a = ap.parse_args()
    torch.set_num_threads(1)

    from sdp_cli.experiments.estimate import job_step_seconds, training_stages
    from sdp_cli.experiments.experiment import load_experiment
    from sdp_cli.experiments.pipeline import loop_configs
    from sdp_cli.experiments.runner import pack
    from sdp_cli.training.train_stack import stack_key

    seeds = {int(s) for s in a.seeds.split(",")}
    runs = {n: c for n, c in loop_configs(a.experiment, load_experiment(a.experiment)).items()
            if c.task in a.tasks.split(",") and c.method in a.methods.split(",") and c.train.seed in seeds
            and c.n_algo == 1}
    if not runs:
        raise SystemExit("no one-iteration runs match")
    st = {s.run: s for s in training_stages(runs)}
    cache: dict = {}

    def seconds(job: list[str]) -> float:
        return job_step_seconds([st[n] for n in job], cache, a.max_s) * max(st[n].steps for n in job)

    groups: dict = {}
    for n, c in runs.items():
        groups.setdefault((c.task, c.method, stack_key(c.task, c.train)), []).append(n)
    print(f"# {a.experiment}, seeds {sorted(seeds)}, --stack {a.stack}: training hours of the stacks (one process)")
    print("| task | method | runs | stacks across sizes | hours | stacks of one size | hours | across / one size |")
    print("|---|---|---|---|---|---|---|---|")
    for (task, method, _), names in groups.items():
        sub = {n: runs[n] for n in names}
        old, new = across_sizes(names, sub, a.stack), pack(sub, a.stack)
        h_old, h_new = sum(map(seconds, old)) / 3600, sum(map(seconds, new)) / 3600
        print(f"| {task} | {method} | {len(names)} | {shape(old, st)} | {h_old:.2f} | {shape(new, st)} | {h_new:.2f} | "
              f"{h_old / h_new:.2f}x |", flush=True)
    print("(stacks as R x B: R runs, batches padded to B)")


if __name__ == "__main__":
    main()

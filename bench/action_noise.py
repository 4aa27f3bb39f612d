"""How precise must a learner be? The memorizer (a perfect learner) with noise on its chunks, beside the fit
error of the trained policies, on their own training instances. Writes results/tasks/action_noise.md.

A trained policy misses the goal either because it did not learn its chunks or because the task cannot forgive
the error a learner is left with. This bench tells the two apart on fig1's runs (``sdp pipeline fig1``):

- the memorizer (:mod:`sdp_cli.policy.memorizer`) of a run's training chunks answers each replanning with its
  nearest chunk plus Gaussian noise of ``sigma`` in the units the networks see (the normalizer's half-range of
  each action coordinate, so 0.01 is 1% of that coordinate's half-range); rows ``[:T_o]`` (the inpainted history)
  are left exact. Two kinds: ``white`` (independent per row and coordinate) and ``offset`` (one draw per chunk
  and coordinate, held over the chunk's rows: a systematic error). Each with the memorizer's own key
  ``(x_t, u_{t-1}, xi)`` (the networks' condition) and with a key without ``u_{t-1}``: noisy state actions
  become jittery controls through inverse dynamics, and a condition on ``u_{t-1}`` feeds that jitter back.
  A third table puts white noise on one block of a state action ``(q part, v)`` at a time (the memorizer's
  own key): ``v[0:3]`` is the quadrotor's linear body velocity, ``v[3:]`` its angular one (UR5: joints 1-3
  and 4-6);
- the trained SDP and DP policies of the same runs: their chunk error against the training chunks, conditioned
  on the true states (every ``--stride``-th start, rows after the history), in the same units; and their own
  rollout on those training instances.

Both are rolled out with the rollout's conventions (:func:`sdp_cli.algorithm.rollout.rollout_policy`, default T_a), under
each conversion of ``--conversions`` (:mod:`sdp_cli.tasks.conversion`; a ``conversion`` column).

    python bench/action_noise.py --runs /work/sweeps/fig1 --tasks ur5-fixed,quadrotor-0 --n-traj 8 --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import copy
import datetime
import platform
from pathlib import Path

import numpy as np
import pandas as pd

SIGMAS = (0.0, 0.001, 0.003, 0.01, 0.03)
BLOCK_SIGMAS = (0.003, 0.01)


def blocks(n_action: int, nv: int) -> dict[str, slice]:
    """The blocks of a state action ``(q part, v)``: ``q part``, ``v[0:3]``, ``v[3:]``."""
    q = n_action - nv
    return {"q part": slice(0, q), "v[0:3]": slice(q, q + 3), "v[3:]": slice(q + 3, n_action)}


def to_costs(task, arrays: dict) -> np.ndarray:
    """TO's cost of each of the dataset's own trajectories, ``(N,)``."""
    return np.array([task.cost(X, U, xi) for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"])])


def replay(policy, arrays: dict, to: np.ndarray, conversion: str | None = None) -> dict:
    """Roll ``policy`` out on the dataset's own instances under ``conversion``; success, cost / ``to`` (TO's,
    ``(N,)``), final distance."""
    import torch

    from sdp_cli.algorithm.rollout import RolloutConfig, evaluate_rollouts, instance_generators, rollout_policy

    xis = arrays["xi"]
    cfg = RolloutConfig(n=len(xis), seed=0, conversion=conversion).validate(policy)
    with torch.no_grad():
        ro = rollout_policy(policy, xis, cfg, generators=instance_generators(0, range(len(xis))))
    ev = evaluate_rollouts(policy.task, ro["X"], ro["U"], xis)
    return {"reached": ev["reached"], "ratio": ev["cost"] / to, "dist": ev["goal_distance"], "t_a": cfg.t_a}


def fit_error(policy, arrays: dict, chunks: np.ndarray, scale: np.ndarray, stride: int) -> tuple[float, float, float]:
    """RMS of ``e = (predicted - training chunk) / scale`` over rows ``T_o:``, over the first row ``T_o``, and of
    its row-to-row part ``e[r+1] - e[r]`` (what white noise is: an error that changes from row to row)."""
    import torch

    from sdp_cli.algorithm.rollout import instance_generators

    N = len(arrays["xi"])
    chunks = chunks.reshape((N, -1) + chunks.shape[1:])                                 # (N, S, T_h, A)
    starts = np.arange(0, chunks.shape[1], stride)
    errs = []
    for i in range(N):
        u_prev = np.concatenate([np.zeros((1, policy.task.nu)), arrays["U"][i, :-1]])[starts]
        with torch.no_grad():
            pred = policy.predict_chunk(np.repeat(arrays["xi"][i:i + 1], len(starts), 0), arrays["X"][i, starts],
                                        u_prev, generator=instance_generators(i, starts))
        errs.append((pred - chunks[i, starts]) / scale)
    e = np.concatenate(errs)[:, policy.T_o:]
    return (float(np.sqrt(np.mean(e ** 2))), float(np.sqrt(np.mean(e[:, 0] ** 2))),
            float(np.sqrt(np.mean(np.diff(e, axis=1) ** 2))))


def summary(r: list[dict]) -> dict:
    reached = np.concatenate([x["reached"] for x in r])
    ratio = np.concatenate([x["ratio"] for x in r])
    return {"success": float(reached.mean()), "cost / TO, median": float(np.median(ratio)),
            "cost / TO, mean": float(np.mean(ratio)),
            "final distance median (m)": float(np.median(np.concatenate([x["dist"] for x in r])))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, required=True, help="a folder of fig1 run folders")
    ap.add_argument("--tasks", default="ur5-fixed,quadrotor-0")
    ap.add_argument("--n-traj", type=int, default=8)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--stride", type=int, default=5, help="every stride-th chunk start is compared")
    ap.add_argument("--conversions", default="inverse-dynamics",
                    help="comma-separated conversions of predicted chunks (inverse-dynamics, tracking)")
    ap.add_argument("--out", type=Path, default=Path("results/tasks/action_noise.md"))
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from sdp_cli.data.artifacts import code_revision
    from sdp_cli.data.chunks import fit_normalizer, load_dataset
    from sdp_cli.policy import load_policy
    from sdp_cli.policy.memorizer import MemorizerPolicy, NoisyMemorizer

    seeds = [int(s) for s in a.seeds.split(",")]
    convs = a.conversions.split(",")
    noisy, fits, by_block = [], [], []
    for task_name in a.tasks.split(","):
        per = {}
        for s in seeds:
            runs = {m: a.runs / f"{task_name}-{m}-n{a.n_traj}-s{s}" for m in ("sdp", "dp")}
            arrays, _, task = load_dataset(runs["sdp"] / "it0" / "data.npz", require_gains=False)
            policies = {m: load_policy(p / "it0" / "policy") for m, p in runs.items()}
            T_h = policies["sdp"].T_h
            mem = MemorizerPolicy(task, arrays, T_h)
            mem_x = copy.copy(mem)                                 # keyed on (x_t, xi) only
            mem_x.scale = mem.scale.copy()
            mem_x.scale[task.nx:task.nx + task.nu] = np.inf
            to = to_costs(task, arrays)
            scale = fit_normalizer(task, arrays, mem.task.action).action_scale.double().numpy()
            for conv in convs:
                for j, sigma in enumerate(SIGMAS):
                    for kind in ("white", "offset"):
                        for key, m in (("(x, u_prev, xi)", mem), ("(x, xi)", mem_x)):
                            r = replay(NoisyMemorizer(m, scale, sigma, kind, seed=s * 100 + j), arrays, to, conv)
                            per.setdefault((conv, kind, key, sigma), []).append(r)
            if mem.task.action == "x":
                for name, sl in blocks(scale.size, task.nv).items():
                    for sigma in BLOCK_SIGMAS:
                        only = np.zeros_like(scale)
                        only[sl] = scale[sl]
                        for conv in convs:
                            r = replay(NoisyMemorizer(mem, only, sigma, "white", seed=s * 100 + 50), arrays, to, conv)
                            per.setdefault((conv, "block", name, sigma), []).append(r)
            for m, pol in policies.items():
                data, _, _ = load_dataset(runs[m] / "it0" / "data.npz", require_gains=False)
                rms, first, jitter = fit_error(pol, data, MemorizerPolicy(task, data, T_h).chunks, scale, a.stride)
                for conv in convs:
                    fits.append({"task": task_name, "method": m, "seed": s, "conversion": conv, "chunk error RMS": rms,
                                 "first row RMS": first, "row-to-row RMS": jitter, **summary([replay(pol, data, to_costs(task, data), conv)])})
        for (conv, kind, key, sigma), r in sorted(per.items(), key=lambda kv: (kv[0][0], kv[0][1],
                                                                                 kv[0][2] != "(x, u_prev, xi)", kv[0][3])):
            if kind == "block":
                by_block.append({"task": task_name, "conversion": conv, "noisy block": key, "sigma": sigma,
                                 **summary(r)})
                continue
            noisy.append({"task": task_name, "conversion": conv, "noise": kind, "key": key, "sigma": sigma,
                          "T_a": r[0]["t_a"], **summary(r)})
    noisy, fits, by_block = pd.DataFrame(noisy), pd.DataFrame(fits), pd.DataFrame(by_block)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = ["# How precise must a learner be? (bench/action_noise.py)", "",
            f"Written by `python bench/action_noise.py --runs {a.runs} --tasks {a.tasks} --n-traj {a.n_traj} "
            f"--seeds {a.seeds} --conversions {a.conversions}` on {stamp}, code revision `{code_revision()}`, {platform.node()} "
            f"({platform.machine()}).", "",
            f"Runs: fig1's SDP and DP at n_traj {a.n_traj}, seeds {a.seeds}, each rolled out on its own "
            f"{a.n_traj} training instances. Success: final distance within the task's tolerance. Cost / TO: the "
            "rollout's cost over TO's on the same instance. sigma is in normalized action units (1.0 = the "
            "half-range of a coordinate over the dataset).", "",
            f"## The memorizer with noise on its chunks ({len(seeds)} seeds x {a.n_traj} instances each)", "",
            noisy.to_markdown(index=False, floatfmt=".3g"), "",
            "## White noise on one block of the state action (key (x, u_prev, xi))", "",
            by_block.to_markdown(index=False, floatfmt=".3g"), "",
            "## The trained policies: chunk error on their training chunks, and their own replay", "",
            f"Chunk error: RMS of (prediction - training chunk) in the same units, conditioned on the true state, "
            f"every {a.stride}th start; rows after the inpainted history, the first of them alone, and the "
            "row-to-row part (RMS of the change of the error from one row to the next; white noise of sigma has "
            "sqrt(2) sigma).", "",
            fits.to_markdown(index=False, floatfmt=".3g"), ""]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()

"""Refinement speed: TO warm-started by a policy vs TO from the naive guess, same instances.

    python bench/refine.py [--policy RUN] [--task double_pendulum] [--n 50] [--t-a 9]

Rolls the policy out on the fixed test set, then solves every instance from the policy's
(X, U) and from the naive interpolation guess (`sdp refine` with its baseline), and prints
mean/median solve time and iterations of both, their ratio, convergence rates, and whether
the casadi problem was rebuilt (it must be built once). The paper reports 4.1 s -> 0.56 s (7x)
on the double pendulum at T_a = 9 and 16.3 s -> 7.8 s on the quadrotor with 9 columns.
Without --policy, a quickly trained SDP policy is used (see bench/rollout.py); pass the
policy of a finished loop (e.g. runs/.../it4/policy) for the fully trained figure.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def outcome_line(d: dict, n: int) -> str:
    """How often the policy guess won: a tie (both solves at the same cost, which ArgminCost keeps from the
    policy) is not a win (:func:`sdp_cli.algorithm.argmin.policy_outcomes`)."""
    from sdp_cli.algorithm.argmin import policy_outcomes

    wins, ties = policy_outcomes(d["inst_winner"], d["inst_pol_cost"], d["inst_base_cost"], d["inst_base_converged"])
    return f"policy guess won {wins}/{n} (cheaper than TO alone, or TO alone failed), tied {ties}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path)
    ap.add_argument("--task", default="double_pendulum")
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--t-a", type=int, default=9)
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)  # the U-Net is tiny: one thread is fastest (and the solves are serial)
    from sdp_cli.data.artifacts import load_npz, load_timing
    from sdp_cli.algorithm.refine import refine
    from sdp_cli.algorithm.rollout import RolloutConfig, rollout
    from sdp_cli.trajopt import build_count

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.policy is None:
            import sys

            sys.path.insert(0, str(Path(__file__).parent))
            from rollout import _train_default

            args.policy = _train_default(args.task, tmp)
        _, s = rollout(args.policy, tmp / "r.npz", RolloutConfig(n=args.n, seed=0, t_a=args.t_a))
        builds = build_count()
        refine(tmp / "r.npz", tmp / "f.npz", workers=args.workers)
        rebuilt = build_count() - builds
        d, _ = load_npz(tmp / "f.npz")
        d.update({k: np.asarray(v) for k, v in load_timing(tmp / "f.npz").items() if k.startswith("inst_")})
    tried = d["inst_pol_iterations"] >= 0  # a diverged rollout is no guess: not solved from it
    pt, bt = d["inst_pol_time"][tried], d["inst_base_time"][tried]
    pi, bi = d["inst_pol_iterations"][tried], d["inst_base_iterations"][tried]
    pc, bc = d["inst_pol_converged"][tried], d["inst_base_converged"][tried]
    print(f"{args.n} instances, policy mean cost {s['mean_cost']:.3g}, T_a = {args.t_a}; "
          f"{int(tried.sum())} rollouts usable as guesses (both solves compared on those)")
    print(f"{'':16s}{'mean time':>12s}{'median time':>13s}{'mean iters':>12s}{'converged':>11s}{'mean cost':>11s}")
    for name, t, it, c, cost in (("naive guess", bt, bi, bc, d["inst_base_cost"][tried]),
                                 ("policy guess", pt, pi, pc, d["inst_pol_cost"][tried])):
        print(f"{name:16s}{t.mean():12.4f}{np.median(t):13.4f}{it.mean():12.1f}{c.mean():11.0%}"
              f"{np.nanmean(np.where(c, cost, np.nan)):11.3g}")
    print(f"speed-up naive / policy: mean time {bt.mean() / pt.mean():.2f}x, iterations {bi.mean() / pi.mean():.2f}x; "
          + outcome_line(d, args.n))
    print(f"casadi problems built during refine (in this process): {rebuilt}")


if __name__ == "__main__":
    main()

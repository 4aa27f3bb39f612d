"""How much chunk error a conversion forgives: the memorizer with white noise on its chunks.

A state-action policy that is nearly right must still reach the goal. The stand-in for such a learner is the
memorizer of the training chunks (:class:`~sdp_cli.policy.memorizer.MemorizerPolicy`, the policies' own key
``(x, u_prev, xi)``) with white Gaussian noise of ``sigma`` on the rows it plays, in the units the networks see
(the normalizer's half-range of each action coordinate: 0.003 is 0.3% of a coordinate's half-range), rolled out
on its own training instances under each conversion (:mod:`sdp_cli.tasks.conversion`).

The rule (decided before any run it judges, issue "A state-action policy must survive its own small errors"):

- a conversion is **admissible** when, at sigma 0, it reproduces TO's cost (ratio 1 within
  :data:`ADMISSIBLE_RTOL`) at every (T_h, T_a) the pipelines use for the task;
- where the paper fixes the conversion (:attr:`Task.paper_conversion`: UR5, "only v_t is used", by RNEA) that
  stays the default; elsewhere the default is the admissible conversion with the higher success summed over
  :data:`RULE_SIGMAS` (a tie keeps ``inverse-dynamics``, the earlier default);
- a task is **tolerant** under a conversion when its success at sigma :data:`TOLERANT_SIGMA` is at least
  :data:`TOLERANT_SUCCESS`, else **fragile**: a learner would have to fit its chunks more precisely than that
  for its rollouts to reach the goal (``sdp check-task`` prints it; it informs and does not fail the check).

The full study (8 training instances x 3 collection seeds, 2 noise draws each) is ``bench/conversion_rule.py``;
``sdp check-task`` runs the same function on its own optima.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.tasks.conversion import CONVERSIONS

RULE_SIGMAS = (0.001, 0.003, 0.01)
TOLERANT_SIGMA, TOLERANT_SUCCESS = 0.003, 0.9
ADMISSIBLE_RTOL = 1e-6
FRAGILE_MEANS = ("fragile: with chunks off by 0.3% of each coordinate's half-range (sigma 0.003), fewer than 90% of "
                 "the memorizer's rollouts reach the goal, so a learned policy that is not more precise than that "
                 "will miss even on its training instances")


def noisy_memorizer_replay(task, arrays: dict, T_h: int, T_a: int, conversion: str, sigma: float,
                           seed: int = 0) -> dict:
    """One noisy-memorizer rollout of ``arrays``' own instances: ``{"reached" (N,), "ratio" (N,)}`` (cost over
    TO's cost on the same instance)."""
    from sdp_cli.data.chunks import fit_normalizer
    from sdp_cli.policy.memorizer import MemorizerPolicy, NoisyMemorizer
    from sdp_cli.algorithm.rollout import RolloutConfig, evaluate_rollouts, rollout_policy

    mem = MemorizerPolicy(task, arrays, T_h)
    scale = fit_normalizer(task, arrays, mem.task.action).action_scale.double().numpy()
    pol = NoisyMemorizer(mem, scale, sigma, "white", seed=seed)
    xis = arrays["xi"]
    ro = rollout_policy(pol, xis, RolloutConfig(n=len(xis), t_a=T_a, conversion=conversion).validate(pol))
    ev = evaluate_rollouts(pol.task, ro["X"], ro["U"], xis)
    to = np.array([task.cost(X, U, xi) for X, U, xi in zip(arrays["X"], arrays["U"], xis)])
    return {"reached": ev["reached"], "ratio": ev["cost"] / to}


def tolerance_table(task, datasets: list[dict], cases, conversions=CONVERSIONS, sigmas=(0.0, *RULE_SIGMAS),
                    draws: int = 2) -> list[dict]:
    """One row per (conversion, T_h, T_a, sigma): success over every instance of ``datasets`` x ``draws`` noise
    draws, the median and the largest relative deviation of cost / TO. Noise seeds are fixed by
    (dataset, draw, sigma), the same for every conversion."""
    rows = []
    for conversion in conversions:
        for T_h, T_a in cases:
            for j, sigma in enumerate(sigmas):
                reached, ratio = [], []
                for d, arrays in enumerate(datasets):
                    for k in range(draws if sigma > 0 else 1):
                        r = noisy_memorizer_replay(task, arrays, T_h, T_a, conversion, sigma,
                                                   seed=10_000 * d + 100 * k + j)
                        reached.append(r["reached"])
                        ratio.append(r["ratio"])
                reached, ratio = np.concatenate(reached), np.concatenate(ratio)
                rows.append({"conversion": conversion, "T_h": T_h, "T_a": T_a, "sigma": sigma,
                             "success": float(reached.mean()), "cost / TO, median": float(np.median(ratio)),
                             "max |cost / TO - 1|": float(np.max(np.abs(ratio - 1)))})
    return rows


def rule_verdict(task, rows: list[dict]) -> dict:
    """The rule (module docstring) on :func:`tolerance_table`'s rows: ``{"admissible": [...], "default": name,
    "why": text, "score": {conversion: success summed over RULE_SIGMAS and cases}, "tolerant": {conversion:
    bool}}``."""
    convs = sorted({r["conversion"] for r in rows}, key=CONVERSIONS.index)
    admissible = [c for c in convs if all(r["max |cost / TO - 1|"] <= ADMISSIBLE_RTOL for r in rows
                                          if r["conversion"] == c and r["sigma"] == 0)]
    score = {c: float(sum(r["success"] for r in rows if r["conversion"] == c and r["sigma"] in RULE_SIGMAS))
             for c in convs}
    tolerant = {c: all(r["success"] >= TOLERANT_SUCCESS for r in rows
                       if r["conversion"] == c and r["sigma"] == TOLERANT_SIGMA) for c in convs}
    fixed = getattr(task, "paper_conversion", None)
    if fixed is not None:
        default, why = fixed, "the paper fixes it"
    elif not admissible:
        default, why = "inverse-dynamics", "no conversion is admissible: the earlier default stays"
    else:
        best = max(score[c] for c in admissible)
        tied = [c for c in admissible if score[c] == best]
        default = "inverse-dynamics" if "inverse-dynamics" in tied else tied[0]
        why = "the admissible conversion with the higher success summed over sigma " + \
              ", ".join(f"{s:g}" for s in RULE_SIGMAS) + (" (a tie keeps inverse-dynamics)" if len(tied) > 1 else "")
    return {"admissible": admissible, "default": default, "why": why, "score": score, "tolerant": tolerant}


def noise_rows_text(task, rows: list[dict]) -> list[str]:
    """``sdp check-task``'s noise-tolerance lines: per (T_h, T_a), the task's default conversion first, then
    the other, success at each of :data:`RULE_SIGMAS`, tolerant or fragile; then what fragile means."""
    default = task.default_conversion
    order = [default] + [c for c in CONVERSIONS if c != default]
    out = []
    for T_h, T_a in sorted({(r["T_h"], r["T_a"]) for r in rows}):
        parts = []
        for c in order:
            got = {r["sigma"]: r["success"] for r in rows if r["conversion"] == c and (r["T_h"], r["T_a"]) == (T_h, T_a)}
            if not got:
                continue
            label = "tolerant" if got.get(TOLERANT_SIGMA, 0.0) >= TOLERANT_SUCCESS else "fragile"
            parts.append(f"{c}{' (default)' if c == default else ''} "
                         + " / ".join(f"{got[s]:.0%}" for s in RULE_SIGMAS if s in got) + f": {label}")
        out.append(f"noise  memorizer + white noise (T_h {T_h}, T_a {T_a}), success at sigma "
                   + " / ".join(f"{s:g}" for s in RULE_SIGMAS) + ": " + "; ".join(parts))
    if any("fragile" in line for line in out):
        out.append(f"noise  {FRAGILE_MEANS}")
    return out

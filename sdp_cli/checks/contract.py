"""The contract a task must meet before anyone trains on it (``sdp check-task NAME``).

Each check gives a row ``{"check", "ok", "value", "limit"}``:

- :func:`model_rows` (no solver): the casadi step (the optimizer's) equals Pinocchio's (the simulation's)
  and the batched rollout step; the control-to-torque map is one definition; the observation map's and
  every accepted action's Jacobians equal central differences on the state manifold; actions read off a
  trajectory give back its controls; costs, constraints, the naive guess and the scene evaluate;
- :func:`optimum_rows` (TO from the naive guess on ``n_traj`` instances): *oracle replay* (the stored
  controls simulated from x0 reproduce the stored states), the *memorizer* (the nearest training chunk,
  :class:`sdp_cli.policy.memorizer.MemorizerPolicy`, rolled out with the rollout's own conventions at each
  (T_h, T_a) reproduces TO's cost to :data:`MEMORIZER_RTOL`), and the timing of the optimum
  (:mod:`sdp_cli.checks.timing`: one step late costs at most 2x).

``tests/test_task_contract.py`` and ``tests/test_memorizer.py`` call the same functions.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from sdp_cli.data.chunks import action_sequence, task_with_action
from sdp_cli.tasks import Task
from sdp_cli.algorithm.solve_jobs import sample_xi
from sdp_cli.trajopt import get_solver
from sdp_cli.policy.registry import get_method
from sdp_cli.tasks import get_task
from sdp_cli.errors import SdpError
from sdp_cli.checks.noise import noise_rows_text, tolerance_table

#: Jacobian entries are O(1); the quadrotor's (Pinocchio's Jlog6 of a rotation within ~1e-4 rad of the
#: reference) match finite differences to 2.5e-6, every other task's to < 1e-8
JAC_ATOL = 1e-5
STEP_ATOL = 1e-9
REPLAY_ATOL = 1e-6
MEMORIZER_RTOL = 1e-6


def _row(check: str, value: float, limit: float, ok: bool | None = None) -> dict:
    ok = bool(value <= limit) if ok is None else bool(ok)
    return {"check": check, "ok": ok, "value": float(value), "limit": float(limit)}


def sample_trajectory(task: Task, n: int = 10, seed: int = 0):
    """``xi, X (n+1, nx), U (n, nu)``: smooth controls inside the bounds from a sampled x0."""
    rng = np.random.default_rng(seed)
    xi = task.sample_xi(rng)
    mid, half = (task.u_ub + task.u_lb) / 2, (task.u_ub - task.u_lb) / 2
    U = mid + 0.02 * half * np.sin(0.3 * np.arange(n)[:, None] + rng.uniform(0, 2 * np.pi, task.nu))
    return xi, task.simulate(task.initial_state(xi), U), U


def manifold_fd(task: Task, f, x, eps=1e-4):
    """Central differences of ``f`` on the manifold: ``(f(x (+) e_i eps) - f(x (-) e_i eps)) / 2 eps``
    (eps 1e-4: near the identity rotation Pinocchio's log map switches to its Taylor branch, and steps
    of 1e-6 across that switch are off by ~1e-6)."""
    cols = []
    for i in range(task.ndx):
        e = np.zeros(task.ndx)
        e[i] = eps
        cols.append((f(task.integrate(x, e)) - f(task.integrate(x, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def model_rows(task: Task) -> list[dict]:
    """The solver-free checks (see the module docstring)."""
    from sdp_cli.algorithm.rollout import step_batch

    xi, X, U = sample_trajectory(task)
    shapes = (xi.shape == (task.n_xi,) and X.shape == (len(U) + 1, task.nx) and task.u_lb.shape == task.u_ub.shape
              == (task.nu,) and bool(np.all(task.u_lb < task.u_ub))
              and (task.actuation is None or np.shape(task.actuation) == (task.nv, task.nu)))
    rows = [_row("dimensions and control bounds", 0.0, 0.0, shapes)]
    err = max(np.abs(np.asarray(task.f_step(X[t], U[t])).ravel() - X[t + 1]).max() for t in range(len(U)))
    rows.append(_row("casadi step = Pinocchio step", err, STEP_ATOL))
    rows.append(_row("batched rollout step = Pinocchio step", np.abs(step_batch(task, X[:-1], U) - X[1:]).max(),
                     STEP_ATOL))
    u = U[1]
    rows.append(_row("control-to-torque: casadi = numpy", np.abs(np.asarray(ca.evalf(task._control_to_tau(ca.DM(u))))
                                                                 .ravel() - task.control_to_tau(u)).max(), 1e-12))
    x = X[len(X) // 2]
    err = np.abs(task.observation_jacobian(x) - manifold_fd(task, task.observation, x)).max()
    rows.append(_row("observation Jacobian vs FD", err, JAC_ATOL,
                     task.observation(x).shape == (task.n_obs,) and err <= JAC_ATOL))
    X0, U0 = task.naive_guess(xi)
    ok = (X0.shape == (task.T + 1, task.nx) and U0.shape == (task.T, task.nu) and np.isfinite(task.cost(X0, U0, xi))
          and np.isfinite(task.constraint_violation(X0, U0, xi)) and np.isfinite(task.goal_distance(X[-1], xi)))
    rows.append(_row("naive guess, cost, constraints, goal distance evaluate", 0.0, 0.0, ok))
    g = task.goal_point(xi)
    ok = (task.path_points(X).shape == (len(X), 3) and (g is None or np.shape(g) == (3,))
          and np.asarray(task.columns).reshape(-1, 3).shape[1] == 3 and task.column_margin >= 0)
    rows.append(_row("scene for plots", 0.0, 0.0, ok))
    for action in task.accepted_actions:
        rows += action_rows(task, action)
    return rows


def action_rows(task: Task, action: str) -> list[dict]:
    """An accepted action: its Jacobian vs FD (state actions) and the controls-from-action round trip."""
    task = task_with_action(task, action)
    xi, X, U = sample_trajectory(task, seed=1)
    rows = []
    if action == "u":
        A = U
    else:
        x = X[3]
        err = np.abs(task.state_action_jacobian(x) - manifold_fd(task, task.state_action, x)).max()
        rows.append(_row(f"action {action}: Jacobian vs FD", err, JAC_ATOL,
                         task.state_action(x).shape == (task.n_action,) and err <= JAC_ATOL))
        A = action_sequence(task, X, U, action)[1:]
    rel = np.abs(task.controls_from_action(X[:-1], A) - U).max() / max(1.0, np.abs(U).max())
    rows.append(_row(f"action {action}: controls from actions = controls", rel, 1e-7))
    return rows


def solve_instances(task: Task, n_traj: int = 2, seed: int = 0, max_attempts: int = 20) -> dict:
    """``n_traj`` converged TO optima from the naive guess (instances ``(seed, i)`` as ``sdp collect``
    draws them): ``{"X", "U", "xi", "K", "Phi"}``."""
    solver = get_solver(task)
    keep = []
    for i in range(max_attempts):
        xi = sample_xi(task, seed, i)
        r = solver.solve(xi, *task.naive_guess(xi))
        if r.converged:
            keep.append((xi, r))
        if len(keep) == n_traj:
            break
    if len(keep) < n_traj:
        raise SdpError(f"task {task.name!r}: only {len(keep)} of {max_attempts} solves converged")
    return {"xi": np.stack([k[0] for k in keep]), **{a: np.stack([getattr(k[1], a) for k in keep])
                                                     for a in ("X", "U", "K", "Phi")}}


def memorizer_rollouts(task: Task, arrays: dict, T_h: int, T_a: int, conversion: str | None = None) -> dict:
    """The memorizer of ``arrays``' chunks rolled out on their own instances under ``conversion`` (None: the
    task's default): :func:`~sdp_cli.algorithm.rollout.evaluate_rollouts`' record plus ``X``, ``U``."""
    from sdp_cli.policy.memorizer import MemorizerPolicy
    from sdp_cli.algorithm.rollout import RolloutConfig, evaluate_rollouts, rollout_policy

    pol = MemorizerPolicy(task, arrays, T_h)
    cfg = RolloutConfig(n=len(arrays["xi"]), t_a=T_a, conversion=conversion).validate(pol)
    ro = rollout_policy(pol, arrays["xi"], cfg)
    return {**ro, **evaluate_rollouts(pol.task, ro["X"], ro["U"], arrays["xi"])}


def memorizer_costs(task: Task, arrays: dict, T_h: int, T_a: int, conversion: str | None = None) -> np.ndarray:
    """Costs of the memorizer of ``arrays``' chunks rolled out on their own instances (N,)."""
    return memorizer_rollouts(task, arrays, T_h, T_a, conversion)["cost"]


def optimum_rows(task: Task, cases, n_traj: int = 2, arrays: dict | None = None) -> tuple[list[dict], list[dict]]:
    """Oracle replay, the memorizer at each ``(T_h, T_a)`` of ``cases`` and the timing of the optima:
    ``(rows, timing records)``."""
    from sdp_cli.checks.timing import WELL_POSED_LATE_RATIO, optimum_timing

    arrays = arrays if arrays is not None else solve_instances(task, n_traj)
    to = np.array([task.cost(X, U, xi) for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"])])
    replay = max(np.abs(task.simulate(task.initial_state(xi), U) - X).max()
                 for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"]))
    rows = [_row("oracle replay: stored controls give the stored states", replay, REPLAY_ATOL)]
    for T_h, T_a in cases:
        rel = np.max(np.abs(memorizer_costs(task, arrays, T_h, T_a) - to) / np.abs(to))
        rows.append(_row(f"memorizer (T_h {T_h}, T_a {T_a}) = TO cost (relative)", rel, MEMORIZER_RTOL))
    timing = [optimum_timing(task, X, U, xi)
              for X, U, xi in zip(arrays["X"], arrays["U"], arrays["xi"])]
    rows.append(_row("one step late costs <= 2x the optimum", max(t["late1"] for t in timing), WELL_POSED_LATE_RATIO))
    return rows, timing


def pipeline_chunk_cases(root: Path = Path(".")) -> set[tuple[str, int, int]]:
    """``(task, T_h, T_a)`` of every chunked policy the experiments in ``root/pipelines`` roll out: the
    collection warm starts (``t_a``, default ``T_h - T_o``) and every evaluated T_a; each run's settings as
    ``sdp pipeline`` resolves them (:func:`sdp_cli.experiments.pipeline.loop_configs`, group defaults included)."""
    from sdp_cli.experiments.experiment import PIPELINES_DIR, load_experiment
    from sdp_cli.experiments.pipeline import loop_configs

    out = set()
    for path in sorted((root / PIPELINES_DIR).glob("*.yaml")):
        for cfg in loop_configs(path.stem, load_experiment(path.stem, root)).values():
            if not get_method(cfg.train.method).chunked:
                continue
            h, r = int(cfg.train.policy.horizon), cfg.rollout
            t_a = r.t_a if r.t_a is not None else cfg.train.policy.max_t_a
            out |= {(cfg.task, h, int(v)) for v in {t_a, *r.eval_t_a, *r.eval_t_a_last}}
    return out


def pipeline_cases(task_name: str, root: Path = Path(".")) -> list[tuple[int, int]]:
    """The (T_h, T_a) pairs the experiments in ``root/pipelines`` roll out ``task_name``'s chunked policies
    with (:func:`pipeline_chunk_cases`), plus the defaults (T_h 32, T_a 31)."""
    T = get_task(task_name).T
    cases = {(32, 31)} | {(h, a) for t, h, a in pipeline_chunk_cases(root) if t == task_name}
    return sorted((h, a) for h, a in cases if h <= T + 1)


def parse_cases(text: str) -> list[tuple[int, int]]:
    """``"32:31,64:63"`` -> ``[(32, 31), (64, 63)]`` (``SdpError`` otherwise)."""
    try:
        pairs = [tuple(int(v) for v in c.split(":")) for c in text.split(",")]
        if all(len(p) == 2 for p in pairs):
            return pairs
    except ValueError:
        pass
    raise SdpError(f"--cases must be T_h:T_a pairs separated by commas, e.g. 32:31,64:63; got {text!r}")


def check_task(name: str, n_traj: int = 2, cases: str | None = None, solve: bool = True, echo=print) -> int:
    """``sdp check-task``: every check as a pass/fail line through ``echo``; the number of checks, or
    ``SdpError`` naming the failed ones."""
    t = get_task(name)
    if n_traj <= 0:
        raise SdpError(f"--n-traj must be > 0, got {n_traj}")
    if cases and not solve:
        raise SdpError("--cases sets the memorizer's (T_h, T_a), a check that needs TO optima: drop --no-solve")
    pairs = parse_cases(cases) if cases else pipeline_cases(name)
    rows, noise = model_rows(t), []
    if solve:
        arrays = solve_instances(t, n_traj)
        rows += optimum_rows(t, pairs, n_traj, arrays)[0]
        if t.action != "u":   # how much chunk error each conversion forgives (informs; never fails the check)
            noise = noise_rows_text(t, tolerance_table(t, [arrays], pairs))
    width = max(len(r["check"]) for r in rows)
    for r in rows:
        echo(f"{'pass' if r['ok'] else 'FAIL'}  {r['check']:<{width}}  {r['value']:.3g} (limit {r['limit']:.3g})")
    for line in noise:
        echo(line)
    failed = [r["check"] for r in rows if not r["ok"]]
    if failed:
        raise SdpError(f"task {name!r} fails {len(failed)} of {len(rows)} checks: {'; '.join(failed)}")
    return len(rows)

"""The paper's own solver on our problems: aligator's ProxDDP beside fatrop, our box-FDDP and crocoddyl's
BoxFDDP, on the same instances. Prints the transcription check, then one table; ``--out`` writes it as markdown.

    bash bench/anchors/setup.sh                       # once: .venv-anchors/ and bench/anchors/build/
    python bench/aligator_compare.py --n 50 [--tasks double_pendulum,ur5-rinit,quadrotor-0] [--out FILE]

Runs in the project's environment; the references run as separate processes in .venv-anchors (never a
dependency of sdp): aligator's ProxDDP through ``bench/anchors/build/proxddp_solve`` (C++, libaligator 0.19.1),
crocoddyl 3.2.1 through ``bench/crocoddyl_compare.py --exchange``. Instances and results go through files.

- **Transcription check first** (C++ ``check`` mode): on a random trajectory (states near the instance's start,
  controls uniform in the bounds) aligator's total cost and every ``x_{t+1} = f(x_t, u_t)`` against
  ``task.cost`` and ``task.step``; a task whose errors exceed ``EXACT`` (1e-10, relative for the cost) is left
  out of the solves with that reason.
- **Instances**: the evaluation set of fig2 (:func:`sdp_cli.algorithm.rollout.evaluation_xis`, test seed 0), the first
  ``--n``, from the task's naive guess.
- **ProxDDP grid, fixed before any run**: tol {1e-3, 1e-4} x mu_init {1e-2, 1e-4} x rollout {linear,
  nonlinear}, max_iters 1000; Gauss-Newton Hessians, aligator's default step acceptance (non-monotone line
  search), one thread. Then from fatrop's optimum as a warm start, every setting.
- **Rules at the others' solutions**: each solver warm-started at each other's solution (the controls, and the
  states of their rollout): iterations it takes (0: its stopping rule accepts the point), and crocoddyl's own
  measure ``|d1 + d2/2|`` (its 3.x stopping criterion) at each solution.
- **Columns**: converged (the solver's own flag; ours also checks its constraint violation); reached (ours, as
  bench/to_alone.py: converged, and the rollout of its controls clipped to the bounds ends within the task's
  goal tolerance with state constraints violated by at most ``VIOLATION_TOL`` = 1e-6; bound violation of the raw
  controls is its own column); iterations median/mean; mean cost over the converged, re-evaluated by
  ``task.cost`` on that rollout; CPU seconds per solve (process CPU time: the C++ program's own clock, our
  solvers' ``time.process_time`` around the call, fatrop unguarded in this process (``SDP_SOLVE_TIMEOUT=0``), both
  after an untimed first solve that builds their compiled functions; our box-FDDP solves the batch at once, its time is the
  batch's CPU time / n).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ANCHORS = ROOT / os.environ.get("SDP_ANCHORS_ENV", ".venv-anchors")
CROC_PY = ANCHORS / "croc" / "bin" / "python"
BIN = ROOT / "bench" / "anchors" / "build" / "proxddp_solve"
SETTINGS = [(tol, mu, ro) for tol in (1e-3, 1e-4) for mu in (1e-2, 1e-4) for ro in ("linear", "nonlinear")]
RULE_SETTING = (1e-4, 1e-2, "linear")   # ProxDDP's rule in the cross table: aligator's defaults, tol 1e-4
MAX_ITERS = 1000
EXACT = 1e-10
VIOLATION_TOL = 1e-6
TASKS = "double_pendulum,ur5-rinit,quadrotor-0"
CROC_TASKS = ("pendulum", "double_pendulum", "quadrotor-0")   # + ur5-*: what bench/crocoddyl_compare.py can express (quadrotor-0: floor and ceiling left out, checked on the solutions by "reached")


def anchors_missing() -> str | None:
    if not CROC_PY.exists() or not BIN.exists():
        return (f"the reference environment is not here ({ANCHORS.name}/ and {BIN.relative_to(ROOT)}): "
                "create it with `bash bench/anchors/setup.sh`")
    return None


# ------------------------------------------------------------------ files shared with the C++ side
def _fmt(v) -> str:
    return " ".join(f"{x:.17g}" for x in np.ravel(np.asarray(v, dtype=float)))


def write_kv(path: Path, items: list[tuple[str, object]], first: str | None = None) -> None:
    lines = [first] if first else []
    lines += [f"{k} {_fmt(v)}" for k, v in items]
    path.write_text("\n".join(lines) + "\n")


def read_kv(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts:
            out[parts[0]] = np.array([float(p) for p in parts[1:]])
    return out


def target(task, xi: np.ndarray) -> np.ndarray:
    """The instance's target point (UR5: the reach target; the quadrotor: the goal; the pendulums: unused)."""
    return np.asarray(xi[task.nx:task.nx + 3], dtype=float) if len(xi) >= task.nx + 3 else np.zeros(3)


def problem_files(task, d: Path) -> None:
    """problem.txt (and urdf.txt for the URDF robots): what proxddp_solve.cpp transcribes."""
    S = np.eye(task.nv, task.nu) if task.actuation is None else np.asarray(task.actuation, dtype=float)
    items = [("T", task.T), ("dt", task.dt), ("u_lb", task.u_lb), ("u_ub", task.u_ub),
             ("actuation", S.ravel(order="F"))]
    if task.name in ("pendulum", "double_pendulum"):
        from sdp_cli.tasks import pendulum as p

        items += [("n_links", task.n_links), ("body_mass", p.BODY_MASS), ("body_radius", p.BODY_RADIUS),
                  ("link_length", p.LINK_LENGTH), ("frame", task.tip), ("goal", task.goal),
                  ("W_GOAL", p.W_GOAL), ("W_U", p.W_U), ("W_GOAL_T", p.W_GOAL_T)]
    elif task.name.startswith("ur5"):
        from sdp_cli.tasks import ur5 as m

        items += [("frame", task.ee)] + [(k, getattr(m, k)) for k in
                                          ("W_Q", "W_V", "W_U", "W_EE", "W_EE_T", "W_TWIST_T", "W_X_T")]
    elif task.name == "quadrotor-0" and task.arrival:
        from sdp_cli.tasks import quadrotor as m

        items += [(k, getattr(m, k)) for k in ("W_P", "W_ROT", "W_V", "W_U", "W_TERMINAL", "W_P_ARRIVE",
                                               "W_V_ARRIVE")]
        items += [("u_hover", task.u_hover), ("z_floor", m.Z_FLOOR), ("z_ceil", m.Z_CEIL)]
    else:
        raise ValueError(f"no transcription of {task.name}")
    if task.name.startswith(("ur5", "quadrotor")):
        from sdp_cli.tasks.robots import URDFS, robots_dir

        rel, free_flyer = URDFS["ur5" if task.name.startswith("ur5") else "hector"]   # as the tasks load them
        (d / "urdf.txt").write_text(f"{robots_dir() / rel}{' free_flyer' if free_flyer else ''}\n")
    write_kv(d / "problem.txt", items, first=f"task {task.name}")


def _run_bin(*args) -> None:
    r = subprocess.run([str(BIN), *map(str, args)], capture_output=True, text=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    if r.returncode != 0:
        raise SystemExit(f"proxddp_solve {' '.join(map(str, args))} failed: {r.stderr.strip()[-500:]}")


def transcription_check(task, d: Path, xi: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """``(relative cost error, max |x_{t+1} aligator - task.step|)`` on a random trajectory."""
    rng = np.random.default_rng(seed)
    x0 = task.initial_state(xi)
    X = np.stack([task.integrate(x0, 0.3 * rng.normal(size=task.ndx)) for _ in range(task.T + 1)])
    X[0] = x0
    U = rng.uniform(task.u_lb, task.u_ub, (task.T, task.nu))
    write_kv(d / "check.txt", [("X", X), ("U", U), ("target", target(task, xi))])
    _run_bin("check", d)
    out = read_kv(d / "check_out.txt")
    ours = task.cost(X, U, xi)
    x_next = out["xnext"].reshape(task.T, task.nx)
    steps = np.stack([task.step(X[t], U[t]) for t in range(task.T)])
    return float(abs(out["cost"][0] - ours) / max(1.0, abs(ours))), float(np.max(np.abs(x_next - steps)))


def proxddp(task, d: Path, xis, starts, setting) -> list[dict]:
    """ProxDDP on every instance from ``starts[i] = (X, U)``: one dict per instance."""
    items = [("n", len(xis))]
    for i, (xi, (X, U)) in enumerate(zip(xis, starts)):
        items += [(f"i{i}.x0", task.initial_state(xi)), (f"i{i}.target", target(task, xi)),
                  (f"i{i}.X", X), (f"i{i}.U", U)]
    write_kv(d / "instances.txt", items)
    tol, mu, ro = setting
    _run_bin("solve", d, tol, mu, ro, MAX_ITERS)
    out = read_kv(d / "solve_out.txt")
    return [{"converged": bool(out[f"i{i}.conv"][0]), "iterations": int(out[f"i{i}.iters"][0]),
             "time": float(out[f"i{i}.cpu"][0]), "U": out[f"i{i}.U"].reshape(task.T, task.nu),
             "X": out[f"i{i}.X"].reshape(task.T + 1, task.nx)} for i in range(len(xis))]


def fatrop(task, xis, starts) -> list[dict]:
    from sdp_cli.trajopt import get_solver

    s = get_solver(task, max_iter=MAX_ITERS)
    s.solve(xis[0], *starts[0], gains=False)          # untimed: whatever is built on the first call
    rows = []
    for xi, (X0, U0) in zip(xis, starts):
        t0 = time.process_time()
        r = s.solve(xi, X0, U0, gains=False)
        rows.append({"converged": bool(r.converged), "iterations": int(r.iterations),
                     "time": time.process_time() - t0, "U": r.U, "X": r.X})
    return rows


def box_fddp(task, xis, starts) -> list[dict]:
    from sdp_cli.trajopt.ddp import DDPSolver

    solver = DDPSolver(task, max_iter=MAX_ITERS)
    x0 = np.array([task.initial_state(x) for x in xis])
    solver.solve_batch(x0[:1], np.asarray(xis)[:1], np.array([starts[0][0]]), np.array([starts[0][1]]),
                       gains=False)                    # untimed: build the compiled maps and kernels
    t0 = time.process_time()
    res = solver.solve_batch(x0, np.asarray(xis),
                             np.array([s[0] for s in starts]), np.array([s[1] for s in starts]), gains=False)
    per = (time.process_time() - t0) / len(xis)
    return [{"converged": bool(r.converged), "iterations": int(r.iterations), "time": per, "U": r.U, "X": r.X}
            for r in res]


def crocoddyl(task, d: Path, xis, starts) -> tuple[list[dict], list[float]]:
    """crocoddyl BoxFDDP from each start, and its |d1 + d2/2| at each start, in .venv-anchors."""
    (d / "croc_in.json").write_text(json.dumps({"task": task.name, "xis": np.asarray(xis).tolist(),
                                                "starts": [[np.asarray(X).tolist(), np.asarray(U).tolist()]
                                                           for X, U in starts], "max_iter": MAX_ITERS}))
    r = subprocess.run([str(CROC_PY), str(ROOT / "bench" / "crocoddyl_compare.py"), "--exchange",
                        str(d / "croc_in.json"), str(d / "croc_out.json")], capture_output=True, text=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"crocoddyl side failed: {r.stderr.strip()[-800:]}")
    out = json.loads((d / "croc_out.json").read_text())
    rows = [{"converged": o["converged"], "iterations": o["iterations"], "time": o["time"],
             "U": np.array(o["U"]), "X": np.array(o["X"])} for o in out["rows"]]
    return rows, [o["stop_at_start"] for o in out["rows"]]


def judge(task, xis, rows: list[dict]) -> None:
    """Add ``reached``, ``cost`` (task.cost on the rollout of the clipped controls) and ``bound_violation``."""
    for xi, r in zip(xis, rows):
        U = np.asarray(r["U"], dtype=float)
        Uc = np.clip(U, task.u_lb, task.u_ub)
        X = task.simulate(task.initial_state(xi), Uc)
        ok = bool(np.all(np.isfinite(X)))
        r["bound_violation"] = float(max(np.max(U - task.u_ub), np.max(task.u_lb - U), 0.0))
        r["cost"] = float(task.cost(X, Uc, xi)) if ok else float("nan")
        r["reached"] = bool(r["converged"] and ok and task.goal_distance(X[-1], xi) <= task.goal_tolerance
                            and task.constraint_violation(X, Uc, xi) <= VIOLATION_TOL)
        r["rollout"] = (X, Uc)


def summary(name: str, rows: list[dict]) -> dict:
    conv = np.array([r["converged"] for r in rows])
    it = np.array([r["iterations"] for r in rows])
    cost = np.array([r["cost"] for r in rows])
    return {"solver": name, "converged %": 100 * conv.mean(), "reached %": 100 * np.mean([r["reached"] for r in rows]),
            "iterations median": float(np.median(it)), "iterations mean": float(it.mean()),
            "cost mean (converged)": float(np.nanmean(cost[conv])) if conv.any() else float("nan"),
            "max bound violation": max(r["bound_violation"] for r in rows),
            "CPU s per solve": float(np.mean([r["time"] for r in rows]))}


def setting_name(s) -> str:
    return f"aligator ProxDDP tol {s[0]:g}, mu_init {s[1]:g}, {s[2]}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default=TASKS)
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--out", type=Path, default=None, help="also write the tables as markdown here")
    a = ap.parse_args()
    missing = anchors_missing()
    if missing:
        print(f"error: {missing}", file=sys.stderr)
        raise SystemExit(1)
    # fatrop in this process, so that its CPU time is this process's (guarded, it solves in a child process, whose
    # time process_time does not count: the rows before 2026-12-07 gave fatrop 1-4 ms per solve that way)
    os.environ.setdefault("SDP_SOLVE_TIMEOUT", "0")
    import pandas as pd

    from sdp_cli.data.artifacts import code_revision
    from sdp_cli.algorithm.rollout import evaluation_xis
    from sdp_cli.tasks import get_task

    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=ROOT).stdout.strip()
    text = [f"`python bench/aligator_compare.py --n {a.n} --tasks {a.tasks}` on {stamp}, commit `{head}` (package "
            f"code `{code_revision()[:12]}`), {platform.node()} ({platform.machine()}, {os.cpu_count()} CPUs, shared); "
            "references: libaligator 0.19.1 with libpinocchio 4.1.0, crocoddyl 3.2.1 with pinocchio 4.0.0 "
            "(bench/anchors/setup.sh).", ""]
    checks, tables, cross = [], [], []
    for name in a.tasks.split(","):
        task = get_task(name)
        with tempfile.TemporaryDirectory(prefix="sdp-anchors-") as tmp:
            d = Path(tmp)
            problem_files(task, d)
            xis = evaluation_xis(task, a.n, 0)
            cost_err, x_err = transcription_check(task, d, xis[0])
            exact = cost_err <= EXACT and x_err <= EXACT
            checks.append({"task": name, "relative cost error": cost_err, "max |x_{t+1} error|": x_err,
                           "exact (<= 1e-10)": exact})
            print(f"{name}: transcription check: relative cost error {cost_err:.2e}, max state error {x_err:.2e}"
                  f" -> {'exact' if exact else 'NOT exact: left out'}", flush=True)
            if not exact:
                continue
            naive = [task.naive_guess(xi) for xi in xis]
            rows = {"fatrop (ours, multiple shooting)": fatrop(task, xis, naive),
                    "box-FDDP (ours)": box_fddp(task, xis, naive)}
            croc_ok = name in CROC_TASKS or name.startswith("ur5")
            if croc_ok:
                rows["crocoddyl BoxFDDP"], _ = crocoddyl(task, d, xis, naive)
            for s in SETTINGS:
                rows[setting_name(s)] = proxddp(task, d, xis, naive, s)
                print(f"  {setting_name(s)} done", flush=True)
            for k, r in rows.items():
                judge(task, xis, r)
                tables.append({"task": name, "start": "naive guess", **summary(k, r)})
            # from fatrop's optimum: every ProxDDP setting
            opt = [r["rollout"] for r in rows["fatrop (ours, multiple shooting)"]]
            for s in SETTINGS:
                r = proxddp(task, d, xis, opt, s)
                judge(task, xis, r)
                tables.append({"task": name, "start": "fatrop's optimum", **summary(setting_name(s), r)})
            # every rule at every solver's solution (the rollouts of their clipped controls)
            sources = {"fatrop": "fatrop (ours, multiple shooting)", "box-FDDP": "box-FDDP (ours)",
                       "ProxDDP": setting_name(RULE_SETTING)}
            if croc_ok:
                sources["crocoddyl"] = "crocoddyl BoxFDDP"
            for src, key in sources.items():
                start = [r["rollout"] for r in rows[key]]
                rules = {"fatrop": fatrop(task, xis, start), "box-FDDP": box_fddp(task, xis, start),
                         "ProxDDP": proxddp(task, d, xis, start, RULE_SETTING)}
                entry = {"task": name, "solution of": src}
                if croc_ok:
                    rules["crocoddyl"], stops = crocoddyl(task, d, xis, start)
                    entry["crocoddyl |d1 + d2/2| median"] = float(np.median(stops))
                for rule, rr in rules.items():
                    it = np.array([x["iterations"] for x in rr])
                    entry[f"{rule}: accepts at 0 it. %"] = 100 * float(np.mean((it == 0) & [x["converged"] for x in rr]))
                    entry[f"{rule}: iterations median"] = float(np.median(it))
                cross.append(entry)
            print(pd.DataFrame([t for t in tables if t["task"] == name]).to_string(), flush=True)
    fmt = ".3g"
    text += ["## Transcription check (random trajectory, aligator against task.cost / task.step)", "",
             pd.DataFrame(checks).to_markdown(index=False, floatfmt=".2e"), "",
             f"## From the naive guess and from fatrop's optimum ({a.n} instances of fig2's evaluation set, test seed 0)", "",
             pd.DataFrame(tables).to_markdown(index=False, floatfmt=fmt), "",
             "## Each stopping rule at each solver's solution (warm start at the rollout of its clipped controls)", "",
             f"ProxDDP's rule: {setting_name(RULE_SETTING)}. Accepts at 0 iterations: the solver stops converged "
             "without a step.", "", pd.DataFrame(cross).to_markdown(index=False, floatfmt=fmt), ""]
    print("\n".join(text))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text("# aligator's ProxDDP beside our solvers and crocoddyl (bench/aligator_compare.py)\n\n"
                         + "\n".join(text))


if __name__ == "__main__":
    main()

"""A small synthetic ``dataset`` artifact with consistent gains, for the learning-side tests.

Each trajectory is a pendulum rollout of a smooth open-loop torque profile (the nominal
trajectory). ``A_t, B_t`` are central finite differences of ``task.step`` in the state
tangent; ``K_t`` is the time-varying LQR feedback of a quadratic cost around the nominal
(backward Riccati on ``A_t, B_t``); ``Phi_t = A_t + B_t K_t``. The closed-loop
law ``u = U_t + K_t (x (-) X_t)`` therefore has exactly these Jacobians to first order,
which is what :mod:`sdp_cli.data.chunks` chains. Follows ``docs/artifacts.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sdp_cli.data.artifacts import save_npz
from sdp_cli.tasks import get_task


def fd_jacobians(task, x, u, eps=1e-6):
    """``A (ndx, ndx)``, ``B (ndx, nu)`` of ``task.step`` at ``(x, u)``, central differences."""
    x1 = task.step(x, u)
    A = np.empty((task.ndx, task.ndx))
    B = np.empty((task.ndx, task.nu))
    for i in range(task.ndx):
        d = np.zeros(task.ndx)
        d[i] = eps
        A[:, i] = (task.difference(x1, task.step(task.integrate(x, d), u))
                   - task.difference(x1, task.step(task.integrate(x, -d), u))) / (2 * eps)
    for i in range(task.nu):
        d = np.zeros(task.nu)
        d[i] = eps
        B[:, i] = (task.difference(x1, task.step(x, u + d)) - task.difference(x1, task.step(x, u - d))) / (2 * eps)
    return A, B


def tvlqr_gains(A, B, Q=1.0, R=0.1):
    """Time-varying LQR gains ``K_t (nu, ndx)`` with ``u = K x`` (sign included)."""
    T, ndx, nu = B.shape
    P = Q * np.eye(ndx)
    K = np.empty((T, nu, ndx))
    for t in reversed(range(T)):
        a, b = A[t], B[t]
        K[t] = -np.linalg.solve(R * np.eye(nu) + b.T @ P @ b, b.T @ P @ a)
        acl = a + b @ K[t]
        P = Q * np.eye(ndx) + K[t].T @ (R * np.eye(nu)) @ K[t] + acl.T @ P @ acl
    return K


def make_trajectories(task, n_traj: int, seed: int = 0, u_scale: float = 1.0):
    """Arrays of a dataset artifact (X, U, K, A, B, Phi, xi, cost, ...)."""
    rng = np.random.default_rng(seed)
    T = task.T
    out = {k: [] for k in ("X", "U", "K", "A", "B", "Phi", "xi", "cost")}
    t = np.arange(T) * task.dt
    for _ in range(n_traj):
        xi = task.sample_xi(rng)
        x0 = task.initial_state(xi)
        amp = u_scale * rng.uniform(2.0, 6.0, task.nu) / task.nu ** 3   # keeps the double pendulum tame
        freq = rng.uniform(0.5, 2.0, task.nu)
        phase = rng.uniform(0, 2 * np.pi, task.nu)
        U = amp * np.sin(2 * np.pi * freq * t[:, None] + phase)
        X = task.simulate(x0, U)
        AB = [fd_jacobians(task, X[s], U[s]) for s in range(T)]
        A = np.stack([a for a, _ in AB])
        B = np.stack([b for _, b in AB])
        K = tvlqr_gains(A, B)
        out["X"].append(X)
        out["U"].append(U)
        out["K"].append(K)
        out["A"].append(A)
        out["B"].append(B)
        out["Phi"].append(A + B @ K)
        out["xi"].append(xi)
        out["cost"].append(task.cost(X, U, xi))
    arrays = {k: np.stack(v) for k, v in out.items()}
    N = n_traj
    arrays.update(iterations=np.zeros(N, int), solve_time=np.zeros(N), converged=np.ones(N, bool),
                  max_violation=np.zeros(N), index=np.arange(N))
    return arrays


def write_dataset(path, task_name="pendulum", n_traj=4, seed=0, T=40, drop=(), u_scale=1.0):
    """Write a synthetic dataset artifact; ``drop`` removes arrays (to test bad input)."""
    task = get_task(task_name, T=T)
    arrays = make_trajectories(task, n_traj, seed, u_scale)
    for k in drop:
        arrays.pop(k)
    dims = {"nq": task.nq, "nv": task.nv, "nx": task.nx, "ndx": task.ndx, "nu": task.nu,
            "n_xi": task.n_xi, "T": task.T, "dt": task.dt}
    return save_npz(Path(path), arrays, kind="dataset",
                    config={"task": task_name, "seed": seed, "n_traj": n_traj, "synthetic": True},
                    task=task_name, task_options={"T": T}, task_params=task.params(), dims=dims)

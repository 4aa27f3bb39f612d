"""Training samples from a ``dataset`` artifact: chunks (diffusion) and pairs (MLP baselines).

Conventions (``T_o = 1``), for a chunk starting at time ``t`` with current state ``x_t``:

- torque control (``a = u``): ``a_hist = u_{t-1}`` (zeros at ``t = 0``), ``o_hist = (obs(x_t), u_{t-1})``,
  ``tau_0 = (u_{t-1}, u_t, ..., u_{t+T_h-2})``; row ``r >= 1`` of ``d tau_0 / d x_t`` is
  ``K_{t+r-1} Phi_{t+r-1,t}``, row 0 (inpainted) is 0;
- state control (``a = g(x)``): ``a_hist = g(x_t)``, ``tau_0 = (g(x_t), ..., g(x_{t+T_h-1}))``,
  row ``r`` is ``G_{t+r} Phi_{t+r,t}`` with ``G`` the Jacobian of ``g``;
- ``Phi_{t,t} = I``, ``Phi_{m+1,t} = Phi_m Phi_{m,t}`` with the stored closed-loop
  ``Phi_m = A_m + B_m K_m``.

Starts ``t = 0 .. T - 1``: every time a rollout can replan (it replans at ``0, T_a, 2 T_a, .. < T``),
so the end of an episode (braking, holding at the goal) is a training condition. Rows past the
episode are *held*, as diffusion_policy's ``SequenceSampler`` pads episode ends: the final state
(state actions: ``g(x_T)``) or the last control (torque: ``u_{T-1}``), with the Jacobian row of what is
held (``G_T Phi_{T,t}``, resp. ``K_{T-1} Phi_{T-1,t}``). A rollout never plays a held row (it stops at T);
they only give the network a consistent target. (Before results version 2 the starts stopped at
``T - T_h + 1``: a perfect memorizer of the chunks then scored 1500x TO's cost on UR5.)

The observation ``o_t = (obs(x_t), u_{t-1})`` depends on ``x_t`` through the task's
observation map (Jacobian ``obs_jac``); ``u_{t-1}`` is treated as given (zero derivative).

Everything is precomputed once as float64 numpy arrays (``N * S * T_h * A * ndx`` floats
for the chunk Jacobians, ``S = T`` starts), then turned into normalized float32
tensors (:meth:`ChunkDataset.tensors`) from which training draws batches by index.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from sdp_cli.data.artifacts import load_npz
from sdp_cli.data.normalizer import Normalizer
from sdp_cli.errors import SdpError
from sdp_cli.tasks import Task, get_task
from sdp_cli.tasks.base import check_task_params

REQUIRED = ("X", "U", "xi")
GAIN_KEYS = ("K", "Phi")


# ---------------------------------------------------------------- loading
def task_options_of(meta: dict) -> dict:
    """The ``get_task`` options a dataset was made with."""
    if "task_options" in meta:
        return dict(meta["task_options"] or {})
    return dict((meta.get("config") or {}).get("task_options") or {})


def task_for_dataset(meta: dict) -> Task:
    """Rebuild the task of a dataset artifact; ``SdpError`` if it cannot be reproduced."""
    name = meta.get("task")
    if not name:
        raise SdpError("dataset has no task name in its metadata")
    task = get_task(name, **task_options_of(meta))
    check_task_params(task, meta.get("task_params"), "dataset")
    return task


def load_dataset(path: str | Path, require_gains: bool = True, task_name: str | None = None):
    """Read and validate a dataset artifact: ``(arrays, meta, task)``."""
    arrays, meta = load_npz(path, kind="dataset")
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise SdpError(f"dataset {path} lacks arrays {', '.join(missing)}")
    if task_name is not None and meta.get("task") != task_name:
        raise SdpError(f"dataset {path} is for task {meta.get('task')!r}, which does not match the "
                       f"policy's task {task_name!r}")
    task = task_for_dataset(meta)
    X, U, xi = arrays["X"], arrays["U"], arrays["xi"]
    N = len(X)
    if N == 0:
        raise SdpError(f"dataset {path} holds no trajectory")
    if X.shape[1:] != (task.T + 1, task.nx) or U.shape[1:] != (task.T, task.nu) or xi.shape != (N, task.n_xi):
        raise SdpError(f"dataset {path} shapes X{X.shape} U{U.shape} xi{xi.shape} do not match task "
                       f"{task.name!r} (T={task.T}, nx={task.nx}, nu={task.nu}, n_xi={task.n_xi})")
    if require_gains:
        lacking = [k for k in GAIN_KEYS if k not in arrays]
        if lacking:
            raise SdpError(f"dataset {path} has no feedback gains ({', '.join(lacking)} missing); "
                           f"Sobolev methods need a dataset from 'sdp collect'")
        if arrays["K"].shape != (N, task.T, task.nu, task.ndx) or arrays["Phi"].shape != (N, task.T, task.ndx, task.ndx):
            raise SdpError(f"dataset {path} gains have shapes K{arrays['K'].shape} Phi{arrays['Phi'].shape}, "
                           f"expected K{(N, task.T, task.nu, task.ndx)} Phi{(N, task.T, task.ndx, task.ndx)}")
        if not np.any(arrays["K"]):
            raise SdpError(f"dataset {path} has all-zero feedback gains K; Sobolev methods need real gains")
    for k in ("X", "U", "xi") + (GAIN_KEYS if require_gains else ()):
        if not np.all(np.isfinite(arrays[k])):
            raise SdpError(f"dataset {path} has non-finite values in {k}")
    return arrays, meta, task


def x_tangent(task: Task, X: np.ndarray) -> np.ndarray:
    """Tangent coordinates ``X (-) X_ref`` (..., ndx) used to fit the state scale."""
    flat = X.reshape(-1, task.nx)
    if task.nx == task.ndx:
        d = flat - flat[0]
    else:
        d = np.stack([task.difference(flat[0], x) for x in flat])
    return d.reshape(X.shape[:-1] + (task.ndx,))


def _u_prev(U: np.ndarray) -> np.ndarray:
    """``u_{t-1}`` for t = 0..T: (N, T+1, nu), zeros at t = 0."""
    return np.concatenate([np.zeros_like(U[:, :1]), U], axis=1)


def action_sequence(task: Task, X: np.ndarray, U: np.ndarray, action: str) -> np.ndarray:
    """``a_{t-1}`` for torque (rows u_{-1}=0, u_0, ..), ``g(x_t)`` for state control: (N, T+1, A)."""
    return _u_prev(U) if action == "u" else task_with_action(task, action).state_action(X)


def fit_normalizer(task: Task, arrays: dict, action: str) -> Normalizer:
    """Fit the normalizer of a policy whose action is ``action`` ("u" for MLPs)."""
    X, U = arrays["X"], arrays["U"]
    acts = U if action == "u" else task_with_action(task, action).state_action(X)
    obs = np.concatenate([task.observation(X), _u_prev(U)], axis=-1)
    return Normalizer.fit(acts, obs, arrays["xi"], x_tangent(task, X))


def task_with_action(task: Task, action: str | None) -> Task:
    """``task`` itself, or a shallow copy whose ``action`` variable is ``action``."""
    if action is None or action == task.action:
        return task
    if action not in task.accepted_actions:
        raise SdpError(f"task {task.name!r} accepts actions {', '.join(task.accepted_actions)}; got {action!r}")
    other = copy.copy(task)
    other.action = action
    return other


# ---------------------------------------------------------------- chunks
class ChunkDataset(Dataset):
    """All chunks of a dataset. Item ``i`` is a dict of float64 arrays (unnormalized):

    ``tau0 (T_h, A)``, ``jac (T_h, A, ndx)`` = d tau_0 / d x_t, ``x_hist (T_o, nx)``,
    ``obs (T_o, n_o)``, ``obs_jac (T_o, n_o, ndx)``, ``a_hist (T_o, A)``, ``xi (n_xi,)``,
    ``traj``, ``t`` (indices). ``with_jacobians=False`` skips ``jac`` (DP needs no gains).
    """

    def __init__(self, task: Task, arrays: dict, T_h: int, T_o: int = 1, action: str | None = None,
                 with_jacobians: bool = True):
        if T_o != 1:
            raise SdpError(f"only T_o = 1 is supported for now, got {T_o}")
        if T_h < T_o + 1 or T_h > task.T + 1:
            raise SdpError(f"T_h must be in [{T_o + 1}, {task.T + 1}] for this dataset, got {T_h}")
        task = task_with_action(task, action)
        self.task, self.T_h, self.T_o = task, int(T_h), int(T_o)
        self.action = task.action
        X, U = arrays["X"], arrays["U"]
        N, T = U.shape[:2]
        self.n_traj, self.T = N, T
        S = T
        self.n_starts = S
        starts = np.arange(S)
        rows = np.minimum(starts[:, None] + np.arange(T_h)[None], T)   # (S, T_h) indices into a_seq, held at T
        a_seq = action_sequence(task, X, U, self.action)          # (N, T+1, A)
        self.tau0 = a_seq[:, rows]                                 # (N, S, T_h, A)
        obs_x = task.observation(X)                                # (N, T+1, n_obs)
        obs = np.concatenate([obs_x, _u_prev(U)], -1)
        Jo = task.observation_jacobian(X)                          # (N, T+1, n_obs, ndx)
        Jo = np.concatenate([Jo, np.zeros(Jo.shape[:2] + (task.nu, task.ndx))], -2)
        self.obs = obs[:, starts, None]                            # (N, S, 1, n_o)
        self.obs_jac = Jo[:, starts, None]                         # (N, S, 1, n_o, ndx)
        self.x_hist = X[:, starts, None]                           # (N, S, 1, nx)
        self.xi = np.broadcast_to(arrays["xi"][:, None], (N, S, arrays["xi"].shape[-1]))
        self.jac = self.chunk_jacobians(task, arrays, T_h, self.action) if with_jacobians else None
        self.a_hist = self.tau0[:, :, :T_o]

    @staticmethod
    def chunk_jacobians(task: Task, arrays: dict, T_h: int, action: str) -> np.ndarray:
        """``d tau_0 / d x_t`` for every start: (N, S, T_h, A, ndx), by chaining K and Phi; rows past
        the episode hold the Jacobian of the held action (the chain stops at the last step)."""
        X, K, Phi = arrays["X"], arrays["K"], arrays["Phi"]
        N, T = K.shape[:2]
        S = T
        starts = np.arange(S)
        ndx = task.ndx
        G = None if action == "u" else task_with_action(task, action).state_action_jacobian(X)  # (N,T+1,A,ndx)
        A_dim = task.nu if action == "u" else G.shape[-2]
        J = np.zeros((N, S, T_h, A_dim, ndx))
        P = np.broadcast_to(np.eye(ndx), (N, S, ndx, ndx)).copy()       # Phi_{t+r,t}, r = 0

        def advance(P, m, last):   # P <- Phi_m P where m <= last (the chain goes on), else held
            return np.where((m <= last)[None, :, None, None], Phi[:, np.minimum(m, T - 1)] @ P, P)

        for r in range(T_h):
            if action == "u":
                if r >= 1:   # row r = u_{min(t+r-1, T-1)}: K_m Phi_{m,t}; P holds Phi_{m,t}
                    J[:, :, r] = K[:, np.minimum(starts + r - 1, T - 1)] @ P
                    if r < T_h - 1:
                        P = advance(P, starts + r - 1, T - 2)   # the last row held is u_{T-1}
            else:            # row r = g(x_{min(t+r, T)}): G Phi_{min(t+r,T),t}
                J[:, :, r] = G[:, np.minimum(starts + r, T)] @ P
                if r < T_h - 1:
                    P = advance(P, starts + r, T - 1)       # the last row held is g(x_T)
        return J

    # Dataset protocol ------------------------------------------------------
    def __len__(self) -> int:
        return self.n_traj * self.n_starts

    def __getitem__(self, i: int) -> dict:
        n, s = divmod(int(i), self.n_starts)
        item = {k: getattr(self, k)[n, s] for k in ("tau0", "x_hist", "obs", "obs_jac", "a_hist", "xi")}
        if self.jac is not None:
            item["jac"] = self.jac[n, s]
        item["traj"], item["t"] = n, s
        return item

    def epoch_size(self) -> int:
        """``E = |D| (T - T_h) / T_h`` chunks (the paper's diffusion epoch), at least 1."""
        return max(1, math.ceil(self.n_traj * (self.T - self.T_h) / self.T_h))

    def tensors(self, norm: Normalizer, device="cpu") -> dict[str, torch.Tensor]:
        """All chunks, normalized, float32, flattened over (traj, start): keys as items."""
        f = lambda a: torch.as_tensor(np.ascontiguousarray(a).reshape((-1,) + a.shape[2:]),
                                      dtype=torch.float64)
        out = {
            "tau0": norm.normalize("action", f(self.tau0)),
            "a_hist": norm.normalize("action", f(self.a_hist)),
            "obs": norm.normalize("obs", f(self.obs)),
            "obs_jac": norm.obs_jacobian(f(self.obs_jac)),
            "xi": norm.normalize("xi", f(self.xi)),
        }
        if self.jac is not None:
            out["jac"] = norm.action_jacobian(f(self.jac))
            if self.action != "u":
                out["a_hist_jac"] = out["jac"][:, : self.T_o]
        return {k: v.to(device=device, dtype=torch.float32).contiguous() for k, v in out.items()}


# ---------------------------------------------------------------- pairs
class PairDataset(Dataset):
    """State-control pairs ``(x_t, u_t, K_t)`` for the MLP baselines, t = 0..T-1.

    Item: ``obs (n_obs,)`` = obs(x_t), ``obs_jac (n_obs, ndx)``, ``u (nu,)``, ``jac (nu, ndx)`` = K_t,
    ``xi``, ``x (nx,)``.
    """

    def __init__(self, task: Task, arrays: dict, with_jacobians: bool = True):
        X, U = arrays["X"], arrays["U"]
        N, T = U.shape[:2]
        self.task, self.n_traj, self.T = task, N, T
        self.x = X[:, :T].reshape(N * T, -1)
        self.obs = task.observation(self.x)
        self.obs_jac = task.observation_jacobian(self.x)
        self.u = U.reshape(N * T, -1)
        self.xi = np.repeat(arrays["xi"], T, axis=0)
        self.jac = arrays["K"].reshape(N * T, task.nu, task.ndx) if with_jacobians else None

    def __len__(self) -> int:
        return len(self.u)

    def __getitem__(self, i: int) -> dict:
        item = {k: getattr(self, k)[i] for k in ("obs", "obs_jac", "u", "xi", "x")}
        if self.jac is not None:
            item["jac"] = self.jac[i]
        return item

    def epoch_size(self) -> int:
        """``E = |D| T`` pairs."""
        return self.n_traj * self.T

    def tensors(self, norm: Normalizer, device="cpu") -> dict[str, torch.Tensor]:
        """Normalized float32 tensors. The MLP observation is ``obs(x)`` only (the first
        ``n_obs`` coordinates of the normalizer's ``obs``)."""
        f = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)
        n = self.obs.shape[-1]
        oc, os_ = norm.obs_center[:n].double(), norm.obs_scale[:n].double()
        out = {
            "obs": (f(self.obs) - oc) / os_,
            "obs_jac": f(self.obs_jac) * norm.x_scale.double() / os_[:, None],
            "u": norm.normalize("action", f(self.u)),
            "xi": norm.normalize("xi", f(self.xi)),
        }
        if self.jac is not None:
            out["jac"] = norm.action_jacobian(f(self.jac))
        return {k: v.to(device=device, dtype=torch.float32).contiguous() for k, v in out.items()}

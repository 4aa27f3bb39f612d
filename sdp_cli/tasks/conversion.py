"""From a predicted chunk of state actions to controls: the conversion, a strategy over the whole chunk.

A state-action policy (``a_t = g(x_{t+1})``: the quadrotor's ``(dq, v)``, UR5's ``v``) predicts where the
system should be; the controls that get it there are the task's business. :meth:`Task.chunk_controller`
builds one controller per predicted chunk (the ``T_a`` rows to be played, for a batch of instances); the
rollout (Algorithm 2) then asks it for the controls of row ``s`` from the state actually reached:

- ``inverse-dynamics``: each row alone, :meth:`Task.controls_from_action` of the reached state (the one-step
  inverse of the predicted velocity; the paper's "u_t is deduced by inverse dynamics"); nothing feeds back the
  error between the state reached and the state predicted, so a chunk's error is integrated open loop.
- ``tracking``: a time-varying LQR around the predicted chunk. Reference ``r_0`` = the state reached when the
  chunk was predicted, ``r_{s+1}`` = the state of row ``s`` (:meth:`Task.states_from_actions`); feedforward
  ``u_ff,s`` = the inverse dynamics of the predicted pair ``r_s -> r_{s+1}``; gains ``K_s`` from one backward
  Riccati pass over the rows, with the dynamics linearized at ``(r_s, u_ff,s)`` in the state tangent
  (:meth:`Task.tangent_step_jacobians`, from the task's casadi dynamics); ``u_s = clip(u_ff,s + K_s (x_s (-)
  r_s))``. At zero chunk error the reached states are the reference and the controls the feedforward, so it
  replays a stored optimum exactly as ``inverse-dynamics`` does. The weights are the task's
  (:attr:`Task.tracking_scales`: the tolerated error per state coordinate and the control scale; Bryson's
  rule), constants of its code, never tuned on a claim's outcome.

The conversion is a rollout setting, not a task parameter (it stays out of :meth:`Task.params`): one
checkpoint can be rolled out under either. Torque actions (``u``) are played as they are (clipped) under both.
"""

from __future__ import annotations

import numpy as np

from sdp_cli.errors import SdpError

CONVERSIONS = ("inverse-dynamics", "tracking")


def check_conversion(name: str | None) -> str | None:
    """``name`` if it is a conversion (or None: the task's default), else one-line ``SdpError``."""
    if name is not None and name not in CONVERSIONS:
        raise SdpError(f"conversion must be one of {', '.join(CONVERSIONS)}; got {name!r}")
    return name


class InverseDynamicsController:
    """Row ``s`` of ``actions (n, S, A)`` alone, from the state reached: :meth:`Task.controls_from_action`."""

    def __init__(self, task, actions: np.ndarray):
        self.task, self.actions = task, np.asarray(actions, dtype=float)

    def __call__(self, x: np.ndarray, s: int) -> np.ndarray:
        """Controls ``(n, nu)`` for row ``s`` from the reached states ``x (n, nx)``."""
        return self.task.controls_from_action(x, self.actions[:, s])


def riccati_gains(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, Qf: np.ndarray) -> np.ndarray:
    """Gains ``K (S, nu, ndx)`` of the finite-horizon LQR ``min sum_s dx_s'Q dx_s + du_s'R du_s + dx_S'Qf dx_S``
    subject to ``dx_{s+1} = A_s dx_s + B_s du_s``, ``du_s = K_s dx_s``: one backward Riccati pass over
    ``A (S, ndx, ndx)``, ``B (S, ndx, nu)``."""
    S = len(A)
    K = np.empty((S, B.shape[2], A.shape[1]))
    P = Qf
    for s in range(S - 1, -1, -1):
        BP = B[s].T @ P
        K[s] = -np.linalg.solve(R + BP @ B[s], BP @ A[s])
        Acl = A[s] + B[s] @ K[s]
        P = Q + K[s].T @ R @ K[s] + Acl.T @ P @ Acl
        P = 0.5 * (P + P.T)
    return K


class TrackingController:
    """The time-varying LQR around a predicted chunk (module docstring), for a batch of instances.

    ``x0 (n, nx)``: the states reached when the chunk was predicted; ``actions (n, S, A)``: the rows to play."""

    def __init__(self, task, x0: np.ndarray, actions: np.ndarray):
        self.task = task
        x0, actions = np.asarray(x0, dtype=float), np.asarray(actions, dtype=float)
        n, S = actions.shape[:2]
        self.ref = task.states_from_actions(x0, actions)                        # (n, S + 1, nx)
        self.u_ff = task.inverse_dynamics(self.ref[:, :-1], self.ref[:, 1:])     # (n, S, nu)
        q_tol, u_scale = task.tracking_scales()
        Q, R = np.diag(1.0 / np.asarray(q_tol) ** 2), np.diag(1.0 / np.asarray(u_scale) ** 2)
        self.K = np.zeros((n, S, task.nu, task.ndx))
        for i in range(n):
            if not (np.all(np.isfinite(self.ref[i])) and np.all(np.isfinite(self.u_ff[i]))):
                continue   # a non-finite prediction: feedforward NaN, the rollout marks the instance diverged
            AB = [task.tangent_step_jacobians(self.ref[i, s], self.u_ff[i, s]) for s in range(S)]
            self.K[i] = riccati_gains(np.stack([a for a, _ in AB]), np.stack([b for _, b in AB]), Q, R, Q)

    def __call__(self, x: np.ndarray, s: int) -> np.ndarray:
        """Controls ``(n, nu)`` for row ``s`` from the reached states ``x (n, nx)``."""
        t = self.task
        with np.errstate(all="ignore"):
            dx = np.stack([t.difference(r, xx) if np.all(np.isfinite(xx)) and np.all(np.isfinite(r))
                           else np.full(t.ndx, np.nan) for r, xx in zip(self.ref[:, s], np.asarray(x, dtype=float))])
            u = self.u_ff[:, s] + np.einsum("nij,nj->ni", self.K[:, s], dx)
        return np.clip(u, t.u_lb, t.u_ub)

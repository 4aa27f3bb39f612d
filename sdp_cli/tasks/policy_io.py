"""The policy conventions of a task: the observation map ``obs(x)``, the action variable ``a`` (torque
``u`` or the state parts ``x``, ``q``, ``v``) and the controls that realize an action (inverse
dynamics), with their Jacobians in the state tangent. :class:`sdp_cli.tasks.base.Task` inherits them;
a task overrides what differs (UR5's observation, the quadrotor's thrust allocation)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin


class PolicyConventions:
    """Mixin of :class:`~sdp_cli.tasks.base.Task`: uses its ``model``, ``data``, dimensions, ``dt``,
    control bounds, ``action`` and :meth:`control_to_tau`."""

    # Batched over leading axes: x (..., nx). Jacobians are w.r.t. the state tangent
    # (perturbation x (+) dx), so chaining them with K_t and Phi_t is consistent.
    # Defaults: observation = x (identity), action = u (torque) or the part of x named by
    # ``action``. UR5 overrides the observation with (cos q, sin q, v); the quadrotor maps
    # q to dq = q (-) q_ref.

    @property
    def n_obs(self) -> int:
        """Size of the observation map ``obs(x)``."""
        return self.nx

    @property
    def accepted_actions(self) -> tuple[str, ...]:
        """Action variables a policy may use on this task.

        Torque ``u`` always; the state actions ``x``, ``q``, ``v`` only where the controls can be
        recovered from a predicted next state by inverse dynamics, i.e. full actuation
        (``nu == nv``) on a Euclidean configuration space. Tasks with another inverse (the
        quadrotor's thrust allocation) override this.
        """
        if self.nu == self.nv and self.nx == self.ndx:
            return ("u", "x", "q", "v")
        return ("u",)

    def inverse_dynamics(self, x: np.ndarray, x_next: np.ndarray) -> np.ndarray:
        """Controls taking ``x`` to (the velocity of) ``x_next`` in one step: (..., nx) x2 -> (..., nu).

        ``u = rnea(q, v, (v_next - v) / dt)`` through the inverse of the (identity) control-to-torque
        map, clipped to the control bounds: the exact inverse of :meth:`step` when unclipped (the
        configuration of ``x_next`` follows from ``v_next`` in semi-implicit Euler). Fully actuated
        tasks only (see :attr:`accepted_actions`).
        """
        if self.nu != self.nv:
            raise NotImplementedError(f"{type(self).__name__} is underactuated: no inverse dynamics")
        x, x_next = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(x_next, dtype=float))
        flat, flat_next = x.reshape(-1, self.nx), x_next.reshape(-1, self.nx)
        S = np.stack([self.control_to_tau(e) for e in np.eye(self.nu)], axis=1)   # tau = S u
        U = np.empty((len(flat), self.nu))
        for i, (xa, xb) in enumerate(zip(flat, flat_next)):
            q, v = xa[: self.nq], xa[self.nq:]
            U[i] = np.linalg.solve(S, pin.rnea(self.model, self.data, q, v, (xb[self.nq:] - v) / self.dt))
        return np.clip(U, self.u_lb, self.u_ub).reshape(x.shape[:-1] + (self.nu,))

    def controls_from_action(self, x: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Controls ``(..., nu)`` that realize the actions ``a (..., n_action)`` from states ``x (..., nx)``.

        ``u``: ``a`` clipped to the control bounds (the actuators cannot do more). State actions
        predict ``g(x_{t+1})``; the next velocity is ``a``'s velocity part for ``x`` and ``v``, and
        ``(q_{t+1} - q_t) / dt`` for ``q`` (semi-implicit Euler: ``q+ = q + dt v+``); the controls
        come from :meth:`inverse_dynamics`.
        """
        if self.action not in self.accepted_actions:
            raise ValueError(f"task {self.name!r} does not accept action {self.action!r}")
        a = np.asarray(a, dtype=float)
        if self.action == "u":
            return np.clip(a, self.u_lb, self.u_ub)
        x = np.asarray(x, dtype=float)
        q = x[..., : self.nq]
        v_next = (a - q) / self.dt if self.action == "q" else a[..., -self.nv:]
        return self.inverse_dynamics(x, np.concatenate([q, v_next], axis=-1))

    @property
    def n_action(self) -> int:
        """Size of one action ``a_t`` of the policy."""
        return {"u": self.nu, "x": self.ndx, "q": self.nv, "v": self.nv}[self.action]

    def _require_euclidean(self, what: str) -> None:
        if self.nx != self.ndx:
            raise NotImplementedError(f"{type(self).__name__} must override {what} (nx != ndx)")

    def observation(self, x: np.ndarray) -> np.ndarray:
        """Observation map ``obs(x)``: (..., nx) -> (..., n_obs). Default: x."""
        self._require_euclidean("observation")
        return np.asarray(x, dtype=float).copy()

    def observation_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``d obs / d dx``: (..., nx) -> (..., n_obs, ndx). Default: identity."""
        self._require_euclidean("observation_jacobian")
        x = np.asarray(x, dtype=float)
        return np.broadcast_to(np.eye(self.ndx), x.shape[:-1] + (self.ndx, self.ndx)).copy()

    def state_action(self, x: np.ndarray) -> np.ndarray:
        """Action of a state-controlled policy ``a = g(x)``: (..., nx) -> (..., n_action).

        ``action`` "x": x, "q": q, "v": v. Undefined for torque control (``action == "u"``).
        """
        x = np.asarray(x, dtype=float)
        if self.action == "u":
            raise ValueError("state_action is undefined for torque control (action 'u')")
        self._require_euclidean("state_action")
        return {"x": x, "q": x[..., : self.nq], "v": x[..., self.nq:]}[self.action].copy()

    def state_action_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``G = d g / d dx``: (..., nx) -> (..., n_action, ndx)."""
        x = np.asarray(x, dtype=float)
        if self.action == "u":
            raise ValueError("state_action_jacobian is undefined for torque control (action 'u')")
        self._require_euclidean("state_action_jacobian")
        eye = np.eye(self.ndx)
        G = {"x": eye, "q": eye[: self.nv], "v": eye[self.nv:]}[self.action]
        return np.broadcast_to(G, x.shape[:-1] + G.shape).copy()

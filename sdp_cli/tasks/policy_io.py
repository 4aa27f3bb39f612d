"""The policy conventions of a task: the observation map ``obs(x)``, the action variable ``a`` (torque
``u`` or the state parts ``x``, ``q``, ``v``) and the controls that realize an action (inverse
dynamics), with their Jacobians in the state tangent. :class:`sdp_cli.tasks.base.Task` inherits them;
a task overrides what differs (UR5's observation, the quadrotor's thrust allocation)."""

from __future__ import annotations

import functools

import numpy as np
import pinocchio as pin
from sdp_cli.tasks.conversion import InverseDynamicsController, TrackingController, check_conversion
import casadi as ca


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

    # ------------------------------------------------------------ chunk conversion (sdp_cli.tasks.conversion)
    #: the conversion a rollout uses when none is asked for (``sdp rollout --conversion``)
    default_conversion: str = "inverse-dynamics"
    #: the conversion the paper prescribes for this task, if it does (the noise rule keeps it as the default)
    paper_conversion: str | None = None

    def tracking_scales(self) -> tuple[np.ndarray, np.ndarray]:
        """``(tolerated error per state-tangent coordinate (ndx,), control scale (nu,))``: the ``tracking``
        conversion's weights by Bryson's rule (``Q = diag(1/tol^2)``, ``R = diag(1/scale^2)``). Default, for
        joint-space tasks: 0.05 rad of joint angle (the pendulums' goal tolerance), 0.5 rad/s of joint velocity
        (a tenth of a swing-up's peak speed), half the torque range (the actuators' authority)."""
        tol = np.concatenate([np.full(self.nv, 0.05), np.full(self.nv, 0.5)])
        return tol, (self.u_ub - self.u_lb) / 2

    def chunk_controller(self, x0: np.ndarray, actions: np.ndarray, conversion: str | None = None):
        """The controller of one predicted chunk: ``x0 (n, nx)`` the states reached when it was predicted,
        ``actions (n, S, n_action)`` the rows to play; call it as ``controller(x (n, nx), s) -> u (n, nu)``.
        ``conversion``: ``inverse-dynamics`` or ``tracking`` (:mod:`sdp_cli.tasks.conversion`; None: the
        task's :attr:`default_conversion`). Torque actions are clipped and played under both."""
        conversion = check_conversion(conversion) or self.default_conversion
        if self.action == "u" or conversion == "inverse-dynamics":
            return InverseDynamicsController(self, actions)
        return TrackingController(self, x0, actions)

    def state_from_action(self, a: np.ndarray) -> np.ndarray:
        """The state a full-state action names (``action`` "x"): (..., n_action) -> (..., nx). Euclidean: ``a``."""
        self._require_euclidean("state_from_action")
        return np.asarray(a, dtype=float).copy()

    def states_from_actions(self, x0: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """The states a chunk predicts, from the state reached: ``x0 (n, nx), actions (n, S, A) -> (n, S+1, nx)``
        with ``[:, 0] = x0``. ``x``: each row's state; ``v``: ``q`` integrated from ``x0`` with the predicted
        velocities (semi-implicit Euler: ``q+ = q (+) dt v+``); ``q``: the velocities ``(q+ - q) / dt``."""
        x0, actions = np.asarray(x0, dtype=float), np.asarray(actions, dtype=float)
        n, S = actions.shape[:2]
        out = np.empty((n, S + 1, self.nx))
        out[:, 0] = x0
        if self.action == "x":
            out[:, 1:] = self.state_from_action(actions)
            return out
        for s in range(S):
            q = out[:, s, : self.nq]
            if self.action == "v":
                v = actions[:, s]
                q_next = np.stack([pin.integrate(self.model, qq, self.dt * vv) for qq, vv in zip(q, v)])
            else:   # "q" (Euclidean configuration)
                q_next = actions[:, s]
                v = (q_next - q) / self.dt
            out[:, s + 1] = np.concatenate([q_next, v], axis=-1)
        return out

    @functools.cached_property
    def _f_tangent_jacobians(self):
        x, u, dx = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("dx", self.ndx)
        f = self.f_step(self.f_integrate(x, dx), u)
        zero = ca.DM.zeros(self.ndx)
        Jx, Ju = ca.substitute([ca.jacobian(f, dx), ca.jacobian(f, u)], [dx], [zero])
        Jp = ca.substitute(ca.jacobian(self.f_integrate(x, dx), dx), dx, zero)
        return ca.Function("tangent_jacobians", [x, u], [self.f_step(x, u), Jx, Ju]), ca.Function("Jp", [x], [Jp])

    def tangent_step_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``A (ndx, ndx), B (ndx, nu)``: the step ``x+ = f(x, u)`` linearized in the state tangent,
        ``f(x (+) dx, u + du) (-) f(x, u) = A dx + B du`` to first order; from the task's casadi dynamics."""
        jac, jp = self._f_tangent_jacobians
        f, Jx, Ju = (np.asarray(m, dtype=float) for m in jac(x, u))
        if self.nx == self.ndx:
            return Jx, Ju
        Jm = np.linalg.pinv(np.asarray(jp(f.ravel()), dtype=float))   # left inverse of the chart at f(x, u)
        return Jm @ Jx, Jm @ Ju

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

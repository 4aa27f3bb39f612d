"""The task interface: one optimal control problem family (eq. (1) of the paper).

A task owns

- the robot model (numerical Pinocchio model and its casadi translation);
- the dimensions: configuration ``nq``, velocity ``nv``, state ``nx = nq + nv``, state
  tangent ``ndx = 2 nv`` (``nx != ndx`` for free-flyers), control ``nu``; ``dt``, horizon ``T``;
- the distribution P of task parameters ``xi (n_xi,)`` (:meth:`Task.sample_xi`) and the
  initial state ``x0(xi)``;
- running and terminal costs, control bounds and state constraints ``h(x, xi) <= 0``,
  all as casadi functions (the optimizer transcribes them, simulation evaluates them);
- the naive initial guess ``Interpolate(x0, x_target)``;
- the discrete dynamics: semi-implicit Euler ``v+ = v + dt aba(q, v, u)``,
  ``q+ = integrate(q, dt v+)``, identical in the optimizer (casadi) and in numerical
  simulation (Pinocchio), so that RNEA inverts a step exactly;
- the policy conventions (action variable, observation map, controls from an action), used by the
  learning side and inherited from :class:`sdp_cli.tasks.policy_io.PolicyConventions`;
- a scene for plots: where the robot's path goes (:meth:`Task.path_points`), the goal
  (:meth:`Task.goal_point`), obstacles (``columns``, ``column_margin``), ``z_bounds``, ``base_marker``.

The contract every registered task meets is checked by ``tests/test_task_contract.py``
(casadi step vs Pinocchio, observation and action Jacobians vs finite differences on the
manifold, the controls-from-action round trip of every accepted action, a short rollout,
the scene); adding a task is one module plus :func:`sdp_cli.tasks.register`, as the toy task
of that test shows.

Gains and state Jacobians live in the tangent space: ``K_t (nu, ndx)``,
``dx_{t+1}/dx_t (ndx, ndx)``, with perturbations applied through :meth:`Task.integrate`.
"""

from __future__ import annotations

import functools
import hashlib
from abc import ABC, abstractmethod
import json

import casadi as ca
import numpy as np
import pinocchio as pin

from sdp_cli.dynamics.casadi_model import CasadiModel
from sdp_cli.errors import SdpError
from sdp_cli.tasks.policy_io import PolicyConventions


class Task(PolicyConventions, ABC):
    """Base class of every task. Subclasses set the attributes below in ``__init__``."""

    #: registered name (``sdp collect --task NAME``)
    name: str
    model: pin.Model
    dt: float
    T: int
    nu: int
    n_xi: int
    #: control bounds (nu,)
    u_lb: np.ndarray
    u_ub: np.ndarray
    #: number of state constraints h(x, xi) <= 0 (applied to x_1..x_T)
    n_h: int = 0
    #: action variable of the policy: "u" (torque), "x", "q" or "v"
    action: str = "u"
    #: default alpha_Sobolev of this task (paper Sec. IV: 1.0, except 1e-3 on the quadrotor)
    sobolev_alpha: float = 1.0
    #: name of the compiled optimizer library; variants whose OCPs are the same casadi
    #: functions (they differ only in how xi is sampled) share one (default: ``name``)
    compile_family: str | None = None
    #: actuation ``tau = S u`` (nv, nu), the one definition used by casadi and numpy; None: identity
    actuation: np.ndarray | None = None

    # scene drawn by the plots (``sdp plot-dataset``, the report's trajectories)
    #: vertical columns (k, 3) of (cx, cy, radius), m
    columns: np.ndarray = np.zeros((0, 3))
    #: margin the state constraint adds around each column (m), drawn dashed
    column_margin: float = 0.0
    #: (z_min, z_max) of the workspace, or None
    z_bounds: tuple | None = None
    #: a fixed point drawn as the robot's base, or None
    base_marker: tuple | None = None

    def __init__(self) -> None:
        self.data = self.model.createData()
        self.cmodel = CasadiModel(self.model)
        self._step_maps: dict[int, ca.Function] = {}

    # ------------------------------------------------------------ dimensions
    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    @property
    def nx(self) -> int:
        return self.nq + self.nv

    @property
    def ndx(self) -> int:
        return 2 * self.nv

    def dims(self) -> dict:
        """Dimensions recorded in every dataset artifact (``meta["dims"]``)."""
        return {"nq": self.nq, "nv": self.nv, "nx": self.nx, "ndx": self.ndx, "nu": self.nu,
                "n_xi": self.n_xi, "T": self.T, "dt": self.dt}

    def params(self) -> dict:
        """Everything that defines this task instance (stored in artifacts).

        ``model_id`` identifies the problem itself (:attr:`model_id`): an artifact made for
        another definition of the same task name is refused (:func:`check_task_params`).
        """
        return {"name": self.name, "dt": self.dt, "T": self.T, "model_id": self.model_id}

    @functools.cached_property
    def model_id(self) -> str:
        """Hash of the robot model's numbers (joint types and placements, inertias, limits,
        gravity) and of the OCP's casadi functions (dynamics, costs with their weights,
        constraints): changes whenever a constant of the problem does."""
        h = hashlib.sha256()
        m = self.model
        h.update(" ".join(j.shortname() for j in m.joints).encode())
        for p in m.jointPlacements:
            h.update(np.asarray(p.homogeneous, dtype=np.float64).tobytes())
        for i in m.inertias:
            h.update(np.r_[i.mass, i.lever, np.asarray(i.inertia).ravel()].astype(np.float64).tobytes())
        for a in (m.effortLimit, m.gravity.linear, self.u_lb, self.u_ub):
            h.update(np.asarray(a, dtype=np.float64).tobytes())
        for f in (self.f_step, self.f_running_cost, self.f_terminal_cost, self.f_state_constraints):
            h.update(f.serialize().encode())
        return h.hexdigest()[:16]

    # --------------------------------------------------- task distribution P
    @abstractmethod
    def sample_xi(self, rng: np.random.Generator) -> np.ndarray:
        """Draw task parameters ``xi ~ P``, shape (n_xi,)."""

    @abstractmethod
    def initial_state(self, xi: np.ndarray) -> np.ndarray:
        """``x0 = x_hat(xi)``, shape (nx,)."""

    @abstractmethod
    def naive_guess(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Interpolate(x0, x_target)``: ``X (T+1, nx)``, ``U (T, nu)``."""

    # ------------------------------------------------------ symbolic problem
    @abstractmethod
    def _running_cost(self, x, u, xi):
        """casadi expression of ``l_t(x, u; xi)``."""

    @abstractmethod
    def _terminal_cost(self, x, xi):
        """casadi expression of ``l_T(x; xi)``."""

    def _running_residual(self, x, u, xi):
        """Optional: a casadi vector ``r`` with ``l_t = 1/2 |r|^2`` (weights folded in), as crocoddyl's residual
        costs; box-FDDP then iterates with the Gauss-Newton model ``r_z' r_z`` of the cost Hessian
        (:mod:`sdp_cli.trajopt.ddp`). ``None`` (the default): the cost is not declared as a sum of squares, and
        box-FDDP projects its exact Hessian onto the PSD cone. ``tests/test_tasks_ur5.py`` checks ``1/2 |r|^2`` against
        :meth:`_running_cost`."""
        return None

    def _terminal_residual(self, x, xi):
        """Optional: ``r`` with ``l_T = 1/2 |r|^2`` (see :meth:`_running_residual`); ``None``: not declared."""
        return None

    def _state_constraints(self, x, xi):
        """casadi expression ``h(x; xi)`` (n_h,), feasible when ``h <= 0``."""
        return ca.SX.zeros(0, 1)

    def _control_to_tau(self, u):
        """Generalized forces from controls, casadi: ``S u`` (:attr:`actuation`)."""
        return u if self.actuation is None else ca.mtimes(ca.DM(self.actuation), u)

    def _symbols(self):
        return ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("xi", self.n_xi)

    @functools.cached_property
    def f_step(self) -> ca.Function:
        """``x_{t+1} = f(x_t, u_t)``: semi-implicit Euler, casadi."""
        x, u, _ = self._symbols()
        q, v = x[: self.nq], x[self.nq:]
        a = self.cmodel.aba(q, v, self._control_to_tau(u))
        v_next = v + self.dt * a
        q_next = self.cmodel.integrate(q, self.dt * v_next)
        return ca.Function("step", [x, u], [ca.vertcat(q_next, v_next)], ["x", "u"], ["x_next"])

    @functools.cached_property
    def f_running_cost(self) -> ca.Function:
        x, u, xi = self._symbols()
        return ca.Function("l", [x, u, xi], [self._running_cost(x, u, xi)], ["x", "u", "xi"], ["l"])

    @functools.cached_property
    def f_terminal_cost(self) -> ca.Function:
        x, _, xi = self._symbols()
        return ca.Function("lT", [x, xi], [self._terminal_cost(x, xi)], ["x", "xi"], ["lT"])

    @functools.cached_property
    def f_state_constraints(self) -> ca.Function:
        x, _, xi = self._symbols()
        return ca.Function("h", [x, xi], [self._state_constraints(x, xi)], ["x", "xi"], ["h"])

    @functools.cached_property
    def f_integrate(self) -> ca.Function:
        """``x (+) dx`` on the state manifold, casadi."""
        x, dx = ca.SX.sym("x", self.nx), ca.SX.sym("dx", self.ndx)
        q_next = self.cmodel.integrate(x[: self.nq], dx[: self.nv])
        return ca.Function("integrate", [x, dx], [ca.vertcat(q_next, x[self.nq:] + dx[self.nv:])])

    # ------------------------------------------------------------ numerics
    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One semi-implicit Euler step with Pinocchio's ``aba``: (nx,), (nu,) -> (nx,)."""
        q, v = x[: self.nq], x[self.nq:]
        tau = np.asarray(self.control_to_tau(u), dtype=float)
        v_next = v + self.dt * pin.aba(self.model, self.data, q, v, tau)
        return np.concatenate([pin.integrate(self.model, q, self.dt * v_next), v_next])

    def control_to_tau(self, u: np.ndarray) -> np.ndarray:
        """Generalized forces from controls, numpy: ``S u`` (..., nu) -> (..., nv)."""
        u = np.asarray(u, dtype=float)
        return u.copy() if self.actuation is None else u @ np.asarray(self.actuation).T

    def step_map(self, n: int) -> ca.Function:
        """:attr:`f_step` mapped over ``n`` states (batched simulation), built once per size."""
        if n not in self._step_maps:
            self._step_maps[n] = self.f_step.map(n)
        return self._step_maps[n]

    def simulate(self, x0: np.ndarray, U: np.ndarray) -> np.ndarray:
        """Roll the dynamics out open-loop: ``X (len(U)+1, nx)``."""
        X = np.empty((len(U) + 1, self.nx))
        X[0] = x0
        for t, u in enumerate(U):
            X[t + 1] = self.step(X[t], u)
        return X

    def integrate(self, x: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """``x (+) dx`` with Pinocchio: (nx,), (ndx,) -> (nx,)."""
        q = pin.integrate(self.model, x[: self.nq], dx[: self.nv])
        return np.concatenate([q, x[self.nq:] + dx[self.nv:]])

    def difference(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """``x1 (-) x0`` with Pinocchio: (nx,), (nx,) -> (ndx,)."""
        dq = pin.difference(self.model, x0[: self.nq], x1[: self.nq])
        return np.concatenate([dq, x1[self.nq:] - x0[self.nq:]])

    #: goal distance under which a rollout counts as having reached the goal (m)
    goal_tolerance: float = 0.05
    #: how the report draws this task's trajectories: "distance" (the goal distance over time) or "top"
    #: (the path seen from above, :meth:`path_points` x-y, with the columns)
    report_view: str = "distance"
    #: seconds per TO solve from the naive guess, (fatrop multiple shooting, IPOPT single shooting), used
    #: by ``sdp pipeline --estimate`` (means of results/tasks/TO_alone.md for the built-in tasks)
    reference_solve_s: tuple[float, float] = (0.010, 0.155)
    #: seconds per box-FDDP solve from the naive guess (``--to ddp``; batch-amortized, results/tasks/TO_alone.md),
    #: for the estimate of loops whose TO is the DDP; None: the multiple-shooting time stands in
    reference_ddp_s: float | None = None

    def path_points(self, X: np.ndarray) -> np.ndarray:
        """3D points of a trajectory for plots: (T+1, nx) -> (T+1, 3). Default: the last frame."""
        fid = self.model.nframes - 1
        out = np.empty((len(X), 3))
        for t, x in enumerate(np.asarray(X, dtype=float)):
            pin.framesForwardKinematics(self.model, self.data, x[: self.nq])
            out[t] = self.data.oMf[fid].translation
        return out

    def goal_point(self, xi: np.ndarray) -> np.ndarray | None:
        """The goal position (3,) of instance ``xi`` for plots, or None."""
        return None

    def goal_distance(self, x: np.ndarray, xi: np.ndarray) -> float:
        """Distance of state ``x`` (nx,) to the task's goal (m): the ``reached`` flag of rollouts."""
        raise NotImplementedError(f"{type(self).__name__} defines no goal distance")

    def cost(self, X: np.ndarray, U: np.ndarray, xi: np.ndarray) -> float:
        """The true objective ``J(X, U; xi)`` of eq. (1)."""
        run = self.f_running_cost.map(len(U))(X[:-1].T, U.T, np.repeat(xi[:, None], len(U), 1))
        return float(run.full().sum() + float(self.f_terminal_cost(X[-1], xi)))

    def terminal_costs(self, X: np.ndarray, xis: np.ndarray) -> np.ndarray:
        """The terminal term ``l_T(x_T; xi)`` of :meth:`cost` per instance: ``X (N, T+1, nx)``, ``xis (N, n_xi)``
        -> ``(N,)``; inf for a trajectory with non-finite entries (a diverged rollout)."""
        out = np.full(len(xis), np.inf)
        for i, (Xi, xi) in enumerate(zip(X, xis)):
            if np.all(np.isfinite(Xi)):
                out[i] = float(self.f_terminal_cost(Xi[-1], xi))
        return out

    def state_constraint_groups(self) -> dict[str, slice]:
        """Named groups of the rows of ``h`` (e.g. the quadrotor's ``floor_ceiling`` and ``obstacles``), so
        that an evaluation can say which constraint a rollout broke; empty groups are left out."""
        return {"state": slice(0, self.n_h)} if self.n_h else {}

    def violations_by_group(self, X: np.ndarray, U: np.ndarray, xi: np.ndarray) -> dict[str, float]:
        """Max violation per group (0 when feasible): ``controls`` (the bounds) and each
        :meth:`state_constraint_groups` group over x_1..x_T. ``X (T+1, nx)``, ``U (T, nu)``, ``xi (n_xi,)``."""
        out = {"controls": max(0.0, float(np.max(U - self.u_ub, initial=0.0)), float(np.max(self.u_lb - U, initial=0.0)))}
        if self.n_h:
            h = self.f_state_constraints.map(len(X) - 1)(X[1:].T, np.repeat(xi[:, None], len(X) - 1, 1)).full()
            for name, rows in self.state_constraint_groups().items():
                out[name] = max(0.0, float(np.max(h[rows], initial=0.0)))
        return out

    def violations_per_instance(self, X: np.ndarray, U: np.ndarray, xis: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`violations_by_group` of a batch: ``X (N, T+1, nx)``, ``U (N, T, nu)``, ``xis (N, n_xi)`` ->
        ``{group: (N,)}``; inf for a trajectory with non-finite entries (a diverged rollout)."""
        out = {g: np.full(len(xis), np.inf) for g in ("controls", *self.state_constraint_groups())}
        for i, (Xi, Ui, xi) in enumerate(zip(X, U, xis)):
            if np.all(np.isfinite(Xi)) and np.all(np.isfinite(Ui)):
                for g, v in self.violations_by_group(Xi, Ui, xi).items():
                    out[g][i] = v
        return out

    def constraint_violation(self, X: np.ndarray, U: np.ndarray, xi: np.ndarray) -> float:
        """Max violation of control bounds and state constraints (0 when feasible)."""
        return max(self.violations_by_group(X, U, xi).values())


def check_task_params(task: Task, stored: dict | None, what: str) -> None:
    """Refuse an artifact (``what``) whose recorded task parameters differ from ``task`` as built here."""
    if stored is None:
        return

    def norm(d):
        return json.loads(json.dumps(d, sort_keys=True, default=float))

    here = task.params()
    if norm(here) == norm(stored):
        return
    if stored.get("model_id") != here["model_id"]:
        raise SdpError(f"{what} was made for another definition of task {task.name!r} (model/cost identity "
                       f"{stored.get('model_id', 'unrecorded')}, this sdp builds {here['model_id']}); "
                       f"re-create it with this version")
    diff = sorted(k for k in set(here) | set(stored) if norm(here.get(k)) != norm(stored.get(k)))
    raise SdpError(f"{what} task parameters differ from task {task.name!r} as built here in: {', '.join(diff)}")


class StartGoalTask(Task):
    """A task whose instances are ``xi = [x0 (nx), goal position (3)]`` (UR5 reach, quadrotor)."""

    report_view = "top"

    def initial_state(self, xi: np.ndarray) -> np.ndarray:
        return np.asarray(xi, dtype=float)[: self.nx].copy()

    def target(self, xi: np.ndarray) -> np.ndarray:
        """Goal position (3,)."""
        return np.asarray(xi, dtype=float)[self.nx:self.nx + 3].copy()

    def goal_point(self, xi: np.ndarray) -> np.ndarray:
        return self.target(xi)

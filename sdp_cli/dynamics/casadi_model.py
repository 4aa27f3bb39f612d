"""A casadi translation of a Pinocchio model: kinematics, RNEA and ABA.

The PyPI ``pin`` wheel has no ``pinocchio.casadi``, so the optimizer gets its symbolic
dynamics from here. The translation reads the numbers of a :class:`pinocchio.Model`
(joint placements, joint types, inertias, frames, gravity) and rebuilds the same
recursive algorithms over the kinematic tree with casadi ``SX``/``MX`` symbols,
following Pinocchio's conventions exactly:

- spatial motions are ``(linear, angular)`` 6-vectors expressed in the joint frame;
- ``liMi = jointPlacement * M_J(q)``; ``v_i = liMi^-1 v_parent + S q_dot``;
- gravity enters as ``a_0 = -model.gravity`` (RNEA and ABA);
- free-flyer configurations are ``(x, y, z, qx, qy, qz, qw)`` with the twist in the
  local frame, and ``integrate`` is ``q * exp6(v)``.

Supported joints: revolute about x/y/z (``JointModelRX/RY/RZ``) and free-flyer, which
covers the double pendulum, the UR5 and the hector quadrotor. ``tests/test_dynamics.py``
checks every function against Pinocchio's ``aba``, ``rnea``, ``framesForwardKinematics``
and ``integrate`` on random states.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pinocchio as pin

from sdp_cli.errors import SdpError

_AXES = {"JointModelRX": 0, "JointModelRY": 1, "JointModelRZ": 2}


def skew(w):
    """(3,) -> (3, 3) cross-product matrix."""
    return ca.vertcat(
        ca.horzcat(0, -w[2], w[1]),
        ca.horzcat(w[2], 0, -w[0]),
        ca.horzcat(-w[1], w[0], 0),
    )


def quat_to_rot(quat):
    """Unit quaternion ``(x, y, z, w)`` -> rotation matrix (Eigen's formula)."""
    x, y, z, w = quat[0], quat[1], quat[2], quat[3]
    return ca.vertcat(
        ca.horzcat(1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        ca.horzcat(2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        ca.horzcat(2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def quat_mul(a, b):
    """Hamilton product of quaternions stored ``(x, y, z, w)``."""
    av, aw = a[0:3], a[3]
    bv, bw = b[0:3], b[3]
    return ca.vertcat(aw * bv + bw * av + ca.cross(av, bv), aw * bw - ca.dot(av, bv))


def exp3_quat(w):
    """Quaternion of the rotation ``exp([w]x)``; Taylor-expanded near 0."""
    th2 = ca.dot(w, w)
    th = ca.sqrt(th2 + 1e-300)
    small = th2 < 1e-8
    s = ca.if_else(small, 0.5 - th2 / 48.0, ca.sin(th / 2) / th)
    c = ca.if_else(small, 1 - th2 / 8.0, ca.cos(th / 2))
    return ca.vertcat(s * w, c)


def exp6_translation(v, w):
    """Translation part of ``exp6((v, w))``: ``V(w) v``; Taylor-expanded near 0."""
    th2 = ca.dot(w, w)
    th = ca.sqrt(th2 + 1e-300)
    small = th2 < 1e-8
    a = ca.if_else(small, 0.5 - th2 / 24.0, (1 - ca.cos(th)) / (th2 + 1e-300))
    b = ca.if_else(small, 1.0 / 6.0 - th2 / 120.0, (th - ca.sin(th)) / (th2 * th + 1e-300))
    W = skew(w)
    return v + a * ca.mtimes(W, v) + b * ca.mtimes(W, ca.mtimes(W, v))


@dataclass(frozen=True)
class _Joint:
    kind: str  # "revolute" or "freeflyer"
    axis: int  # revolute axis index (0, 1, 2); -1 for free-flyer
    parent: int
    idx_q: int
    idx_v: int
    nq: int
    nv: int
    R0: np.ndarray  # joint placement rotation (3, 3)
    p0: np.ndarray  # joint placement translation (3,)
    inertia: np.ndarray  # spatial inertia (6, 6), Pinocchio's (linear, angular) order


class CasadiModel:
    """Symbolic multibody dynamics rebuilt from a Pinocchio model.

    All methods accept casadi ``SX`` or ``MX`` column vectors (or numbers) and return
    casadi expressions: ``q (nq,)``, ``v (nv,)``, ``tau (nv,)``.
    """

    def __init__(self, model: pin.Model):
        self.model = model
        self.nq, self.nv = model.nq, model.nv
        self.gravity = np.concatenate([model.gravity.linear, model.gravity.angular])
        joints = []
        for i in range(1, model.njoints):
            jm = model.joints[i]
            name = jm.shortname()
            if name in _AXES:
                kind, axis = "revolute", _AXES[name]
            elif name == "JointModelFreeFlyer":
                kind, axis = "freeflyer", -1
            else:
                raise SdpError(f"joint type {name} of joint {model.names[i]!r} is not supported")
            M = model.jointPlacements[i]
            joints.append(
                _Joint(kind, axis, model.parents[i], jm.idx_q, jm.idx_v, jm.nq, jm.nv,
                       M.rotation.copy(), M.translation.copy(), model.inertias[i].matrix().copy())
            )
        self.joints = joints

    # ----------------------------------------------------------------- kinematics
    def _joint_transform(self, j: _Joint, q):
        """``M_J(q)`` as ``(R, p)``."""
        if j.kind == "revolute":
            c, s = ca.cos(q[j.idx_q]), ca.sin(q[j.idx_q])
            if j.axis == 0:
                R = ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, c, -s), ca.horzcat(0, s, c))
            elif j.axis == 1:
                R = ca.vertcat(ca.horzcat(c, 0, s), ca.horzcat(0, 1, 0), ca.horzcat(-s, 0, c))
            else:
                R = ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))
            return R, ca.DM.zeros(3, 1)
        qq = q[j.idx_q:j.idx_q + 7]
        return quat_to_rot(qq[3:7]), qq[0:3]

    def _liMi(self, j: _Joint, q):
        Rj, pj = self._joint_transform(j, q)
        R0, p0 = ca.DM(j.R0), ca.DM(j.p0)
        return ca.mtimes(R0, Rj), p0 + ca.mtimes(R0, pj)

    def forward_kinematics(self, q):
        """Placements ``oMi`` of every joint (index 0 is the universe) as ``(R, p)``."""
        oMi = [(ca.DM.eye(3), ca.DM.zeros(3, 1))]
        for j in self.joints:
            R, p = self._liMi(j, q)
            Rp, pp = oMi[j.parent]
            oMi.append((ca.mtimes(Rp, R), pp + ca.mtimes(Rp, p)))
        return oMi

    def frame_placement(self, q, frame: str | int):
        """World placement ``oMf`` of a frame as ``(R (3, 3), p (3,))``."""
        fid = self.model.getFrameId(frame) if isinstance(frame, str) else frame
        if fid >= self.model.nframes:
            raise SdpError(f"unknown frame {frame!r}")
        f = self.model.frames[fid]
        Rp, pp = self.forward_kinematics(q)[f.parentJoint]
        return ca.mtimes(Rp, ca.DM(f.placement.rotation)), pp + ca.mtimes(Rp, ca.DM(f.placement.translation))

    # ------------------------------------------------------------ spatial algebra
    @staticmethod
    def _motion_inv_matrix(R, p):
        """6x6 matrix of ``liMi.actInv`` on motions ``(v, w)``."""
        Rt = R.T
        return ca.vertcat(ca.horzcat(Rt, -ca.mtimes(Rt, skew(p))), ca.horzcat(ca.DM.zeros(3, 3), Rt))

    @staticmethod
    def _cross_motion(m1, m2):
        v1, w1, v2, w2 = m1[0:3], m1[3:6], m2[0:3], m2[3:6]
        return ca.vertcat(ca.cross(w1, v2) + ca.cross(v1, w2), ca.cross(w1, w2))

    @staticmethod
    def _cross_force(m, f):
        v, w, fl, fa = m[0:3], m[3:6], f[0:3], f[3:6]
        return ca.vertcat(ca.cross(w, fl), ca.cross(w, fa) + ca.cross(v, fl))

    @staticmethod
    def _S(j: _Joint):
        if j.kind == "revolute":
            S = np.zeros((6, 1))
            S[3 + j.axis, 0] = 1.0
            return ca.DM(S)
        return ca.DM.eye(6)

    def _first_pass(self, q, v):
        """Per-joint motion-inverse matrices, velocities and joint velocities."""
        Xs, vs, vJs = [], [ca.DM.zeros(6, 1)], []
        for j in self.joints:
            X = self._motion_inv_matrix(*self._liMi(j, q))
            vJ = ca.mtimes(self._S(j), v[j.idx_v:j.idx_v + j.nv])
            Xs.append(X)
            vJs.append(vJ)
            vs.append(ca.mtimes(X, vs[j.parent]) + vJ)
        return Xs, vs, vJs

    # ----------------------------------------------------------------- dynamics
    def rnea(self, q, v, a):
        """Inverse dynamics ``tau = M(q) a + C(q, v) v + g(q)`` (nv,)."""
        Xs, vs, vJs = self._first_pass(q, v)
        n = len(self.joints)
        accs = [ca.DM(-self.gravity)]
        fs = []
        for k, j in enumerate(self.joints):
            S = self._S(j)
            acc = ca.mtimes(Xs[k], accs[j.parent]) + ca.mtimes(S, a[j.idx_v:j.idx_v + j.nv]) \
                + self._cross_motion(vs[k + 1], vJs[k])
            accs.append(acc)
            I = ca.DM(j.inertia)
            fs.append(ca.mtimes(I, acc) + self._cross_force(vs[k + 1], ca.mtimes(I, vs[k + 1])))
        tau = [None] * n
        for k in reversed(range(n)):
            j = self.joints[k]
            tau[k] = ca.mtimes(self._S(j).T, fs[k])
            if j.parent > 0:
                fs[j.parent - 1] = fs[j.parent - 1] + ca.mtimes(Xs[k].T, fs[k])
        return ca.vertcat(*[tau[k] for k in sorted(range(n), key=lambda k: self.joints[k].idx_v)])

    def aba(self, q, v, tau):
        """Forward dynamics ``a = M(q)^-1 (tau - C(q, v) v - g(q))`` (nv,), articulated-body."""
        Xs, vs, vJs = self._first_pass(q, v)
        n = len(self.joints)
        cs = [self._cross_motion(vs[k + 1], vJs[k]) for k in range(n)]
        IA = [ca.DM(j.inertia) for j in self.joints]
        pA = [self._cross_force(vs[k + 1], ca.mtimes(IA[k], vs[k + 1])) for k in range(n)]
        Us, Dinvs, us = [None] * n, [None] * n, [None] * n
        for k in reversed(range(n)):
            j = self.joints[k]
            S = self._S(j)
            U = ca.mtimes(IA[k], S)
            D = ca.mtimes(S.T, U)
            if j.nv == 1:
                Dinv = 1.0 / D
            elif D.is_constant():
                Dinv = ca.DM(np.linalg.inv(np.array(ca.evalf(D))))
            else:
                Dinv = ca.inv(D)
            u = tau[j.idx_v:j.idx_v + j.nv] - ca.mtimes(S.T, pA[k])
            Us[k], Dinvs[k], us[k] = U, Dinv, u
            if j.parent > 0:
                UD = ca.mtimes(U, Dinv)
                Ia = IA[k] - ca.mtimes(UD, U.T)
                pa = pA[k] + ca.mtimes(Ia, cs[k]) + ca.mtimes(UD, u)
                p = j.parent - 1
                IA[p] = IA[p] + ca.mtimes(Xs[k].T, ca.mtimes(Ia, Xs[k]))
                pA[p] = pA[p] + ca.mtimes(Xs[k].T, pa)
        accs = [ca.DM(-self.gravity)]
        qdd = [None] * n
        for k, j in enumerate(self.joints):
            ap = ca.mtimes(Xs[k], accs[j.parent]) + cs[k]
            qdd[k] = ca.mtimes(Dinvs[k], us[k] - ca.mtimes(Us[k].T, ap))
            accs.append(ap + ca.mtimes(self._S(j), qdd[k]))
        return ca.vertcat(*[qdd[k] for k in sorted(range(n), key=lambda k: self.joints[k].idx_v)])

    # ----------------------------------------------------------- configuration
    def integrate(self, q, dv):
        """``q (+) dv`` on the configuration manifold (Pinocchio's ``integrate``)."""
        parts = [None] * len(self.joints)
        for k, j in enumerate(self.joints):
            if j.kind == "revolute":
                parts[k] = q[j.idx_q] + dv[j.idx_v]
            else:
                qq, vv = q[j.idx_q:j.idx_q + 7], dv[j.idx_v:j.idx_v + 6]
                R = quat_to_rot(qq[3:7])
                p = qq[0:3] + ca.mtimes(R, exp6_translation(vv[0:3], vv[3:6]))
                quat = quat_mul(qq[3:7], exp3_quat(vv[3:6]))
                quat = quat * (3 - ca.dot(quat, quat)) / 2  # Pinocchio's first-order normalization
                parts[k] = ca.vertcat(p, quat)
        order = sorted(range(len(self.joints)), key=lambda k: self.joints[k].idx_q)
        return ca.vertcat(*[parts[k] for k in order])

"""Chunks, chained Jacobians and the normalizer, against finite differences of closed-loop simulation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sdp_cli.data.artifacts import load_npz
from sdp_cli.data.chunks import ChunkDataset, PairDataset, fit_normalizer, load_dataset
from sdp_cli.errors import SdpError
from sdp_cli.tasks.pendulum import PendulumTask
from synthetic_dataset import write_dataset

T, T_H = 30, 8


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "syn.npz"
    write_dataset(path, "pendulum", n_traj=3, seed=1, T=T)
    return path


@pytest.fixture(scope="module")
def loaded(dataset):
    return load_dataset(dataset)


def closed_loop(task, arrays, n, t, dx, steps):
    """States x_t..x_{t+steps} and controls u_t..u_{t+steps-1} under u = U_m + K_m (x (-) X_m)."""
    X, U, K = arrays["X"][n], arrays["U"][n], arrays["K"][n]
    x = task.integrate(X[t], dx)
    xs, us = [x], []
    for m in range(t, t + steps):
        u = U[m] + K[m] @ task.difference(X[m], x)
        x = task.step(x, u)
        us.append(u)
        xs.append(x)
    return np.array(xs), np.array(us)


def chunk_fd(task, arrays, n, t, action, eps=1e-5):
    """Central FD of tau_0 w.r.t. the tangent of x_t: (T_h, A, ndx). The closed loop runs to the episode's
    end (T) at most; rows past it hold the last control (torque) or the final state's action."""
    steps = min(T_H - 1, T - t)
    cols = []
    for i in range(task.ndx):
        d = np.zeros(task.ndx)
        d[i] = eps
        tau = []
        for s in (1, -1):
            xs, us = closed_loop(task, arrays, n, t, s * d, steps)
            if action == "u":
                u_prev = arrays["U"][n, t - 1] if t > 0 else np.zeros(task.nu)
                rows = np.vstack([u_prev[None], us])
            else:
                rows = task.state_action(xs)
            tau.append(np.vstack([rows, np.repeat(rows[-1:], T_H - len(rows), 0)]))
        cols.append((tau[0] - tau[1]) / (2 * eps))
    return np.stack(cols, -1)


def held(a, t, length=T_H):
    """Rows t .. t + length - 1 of a sequence, those past its end held at its last row."""
    return a[np.minimum(np.arange(t, t + length), len(a) - 1)]


def test_every_replanning_time_is_a_training_start(loaded):
    """Starts 0 .. T - 1 (every time a rollout can replan), each once per trajectory."""
    arrays, _, task = loaded
    ds = ChunkDataset(task, arrays, T_H)
    assert ds.n_starts == T and len(ds) == 3 * T
    assert ds.epoch_size() == int(np.ceil(3 * (T - T_H) / T_H))        # the paper's E = |D| (T - T_h) / T_h


@pytest.mark.parametrize("t", [0, 5, T - T_H + 1, T - T_H + 2, T - 3, T - 1])
def test_torque_chunk_jacobian_matches_closed_loop_fd(loaded, t):
    arrays, _, task = loaded
    ds = ChunkDataset(task, arrays, T_H)
    n = 1
    item = ds[n * ds.n_starts + t]
    assert item["t"] == t
    np.testing.assert_allclose(item["tau0"][1:], held(arrays["U"][n], t, T_H - 1))   # held at u_{T-1}
    np.testing.assert_allclose(item["a_hist"][0], arrays["U"][n, t - 1] if t else 0.0)
    np.testing.assert_allclose(item["obs"][0], np.r_[arrays["X"][n, t], arrays["U"][n, t - 1] if t else 0.0])
    J = item["jac"]
    assert J.shape == (T_H, task.nu, task.ndx)
    assert np.all(J[0] == 0)
    fd = chunk_fd(task, arrays, n, t, "u")
    np.testing.assert_allclose(J, fd, atol=2e-4 * max(1.0, np.abs(fd).max()))
    assert np.abs(J[1:]).max() > 1e-2  # not trivially zero


@pytest.mark.parametrize("t", [4, T - T_H + 2, T - 1])
@pytest.mark.parametrize("action", ["x", "q", "v"])
def test_state_chunk_jacobian_matches_closed_loop_fd(loaded, action, t):
    arrays, _, task = loaded
    ds = ChunkDataset(task, arrays, T_H, action=action)
    n = 2
    item = ds[n * ds.n_starts + t]
    np.testing.assert_allclose(item["tau0"], ds.task.state_action(held(arrays["X"][n], t)))   # held at g(x_T)
    fd = chunk_fd(ds.task, arrays, n, t, action)
    np.testing.assert_allclose(item["jac"], fd, atol=2e-4 * max(1.0, np.abs(fd).max()))
    np.testing.assert_allclose(item["jac"][0], ds.task.state_action_jacobian(arrays["X"][n, t]))


class CosSinPendulum(PendulumTask):
    """A pendulum whose observation is (cos q, sin q, v), as the UR5's."""

    @property
    def n_obs(self):
        return 2 * self.nq + self.nv

    def observation(self, x):
        q, v = x[..., : self.nq], x[..., self.nq:]
        return np.concatenate([np.cos(q), np.sin(q), v], -1)

    def observation_jacobian(self, x):
        q = x[..., : self.nq]
        J = np.zeros(x.shape[:-1] + (self.n_obs, self.ndx))
        for i in range(self.nq):
            J[..., i, i] = -np.sin(q[..., i])
            J[..., self.nq + i, i] = np.cos(q[..., i])
        for i in range(self.nv):
            J[..., 2 * self.nq + i, self.nv + i] = 1.0
        return J


def test_observation_map_jacobian_in_chunks(loaded):
    arrays, _, _ = loaded
    task = CosSinPendulum(n_links=1, T=T)
    ds = ChunkDataset(task, arrays, T_H)
    item = ds[7]
    x = item["x_hist"][0]
    eps = 1e-6
    fd = np.stack([(task.observation(task.integrate(x, eps * e)) - task.observation(task.integrate(x, -eps * e)))
                   / (2 * eps) for e in np.eye(task.ndx)], -1)
    np.testing.assert_allclose(item["obs_jac"][0, : task.n_obs], fd, atol=1e-8)
    assert np.all(item["obs_jac"][0, task.n_obs:] == 0)  # u_{t-1} is given


def test_normalized_jacobian_matches_fd_in_normalized_units(loaded):
    """d tau0_n / d delta with x = x_t (+) x_scale * delta: the normalizer scales Jacobians consistently."""
    arrays, _, task = loaded
    ds = ChunkDataset(task, arrays, T_H)
    norm = fit_normalizer(task, arrays, "u")
    assert torch.all(norm.x_scale != 1.0)  # a real scaling, not the identity
    tens = ds.tensors(norm)
    n, t = 0, 3
    i = n * ds.n_starts + t
    eps = 1e-4
    cols = []
    for k in range(task.ndx):
        delta = np.zeros(task.ndx)
        delta[k] = eps
        taus = []
        for s in (1, -1):
            dx = s * delta * norm.x_scale.double().numpy()
            _, us = closed_loop(task, arrays, n, t, dx, T_H - 1)
            tau = np.vstack([arrays["U"][n, t - 1][None], us[: T_H - 1]])
            taus.append(norm.normalize("action", torch.as_tensor(tau)).numpy())
        cols.append((taus[0] - taus[1]) / (2 * eps))
    fd = np.stack(cols, -1)
    np.testing.assert_allclose(tens["jac"][i].numpy(), fd, atol=1e-3 * max(1.0, np.abs(fd).max()))
    # normalized values are in [-1, 1] (clip_sample-compatible) and the obs Jacobian is the identity scaled
    assert tens["tau0"].abs().max() <= 1 + 1e-6
    np.testing.assert_allclose(tens["obs_jac"][i, 0, : task.nx].numpy(),
                               np.diag((norm.x_scale / norm.obs_scale[: task.nx]).numpy()), atol=1e-6)


def test_normalizer_round_trip_and_state_dict(loaded):
    arrays, _, task = loaded
    norm = fit_normalizer(task, arrays, "u")
    u = torch.as_tensor(arrays["U"][0])
    np.testing.assert_allclose(norm.unnormalize("action", norm.normalize("action", u)).numpy(), u.numpy(), atol=1e-5)
    keys = set(norm.state_dict())
    assert {"action_scale", "obs_center", "xi_scale", "x_scale"} <= keys


def test_epoch_sizes(loaded):
    arrays, _, task = loaded
    ds = ChunkDataset(task, arrays, T_H)
    assert len(ds) == 3 * T                     # starts 0 .. T - 1 (test_every_replanning_time_is_a_training_start)
    assert ds.epoch_size() == int(np.ceil(3 * (T - T_H) / T_H))
    pairs = PairDataset(task, arrays)
    assert len(pairs) == pairs.epoch_size() == 3 * T
    np.testing.assert_allclose(pairs[T + 2]["jac"], arrays["K"][1, 2])


def test_bad_datasets(tmp_path, dataset):
    nogain = write_dataset(tmp_path / "nogain.npz", n_traj=2, T=T, drop=("K", "Phi"))
    with pytest.raises(SdpError, match="no feedback gains"):
        load_dataset(nogain)
    load_dataset(nogain, require_gains=False)  # fine for DP / PDDP
    with pytest.raises(SdpError, match="does not match the policy's task 'double_pendulum'"):
        load_dataset(dataset, task_name="double_pendulum")
    arrays, meta = load_npz(dataset)
    with pytest.raises(SdpError, match="T_h"):
        ChunkDataset(PendulumTask(n_links=1, T=T), arrays, T + 5)

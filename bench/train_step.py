"""Time one training step of DP and SDP (and the Sobolev variants) in one run, print ratios.

    python bench/train_step.py [--batch 256] [--horizon 32] [--rounds 12] [--threads N] [--data DATASET]
                               [--csv results/bench/train_step.csv --setting NAME]

``--csv`` appends one row per mode (setting, sizes, medians, ratios to dp, load, torch version) to a
CSV, replacing the rows of the same ``--setting``; ``results/bench/train_step.csv`` is read by the
claims ledger (``sdp report --ledger``, claim "one SDP epoch costs about 2x a DP epoch").

A step is loss + backward + AdamW update on the default conditional U-Net ([24, 24, 32, 32]).
Modes, measured interleaved (round-robin) so that machine load affects all alike; the
median per mode is reported:

- ``dp``            eq. (2) only;
- ``sdp-vjp``       eq. (6) by double backward (projection on the output side): the naive baseline;
- ``sdp-jvp-func``  projection on the x side, forward mode with ``torch.func.jvp``;
- ``sdp-jvp``       projection on the x side, hand-written tangent propagation (the default);
- ``sdp-jvp-half``  the same with ``sobolev_fraction = 0.5`` (Sobolev term on half of each batch).

Wall time and process CPU time are both reported; on a shared machine the CPU-time ratios
(with ``--threads 1``) are the stable ones.

Without ``--data`` the batch is synthetic with the pendulum's sizes (A = 1, ndx = 2, xi (2),
o = (x, u_prev) (3)); with ``--data`` it is drawn from the dataset's chunks.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch
from torch.func import jvp

from sdp_cli.policy.config import TrainConfig
from sdp_cli.policy.diffusion import DiffusionUnetPolicy


def synthetic_batch(B, T_h, A=1, ndx=2, n_o=3, n_xi=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    b = {"tau0": torch.rand(B, T_h, A, generator=g) * 2 - 1, "obs": torch.rand(B, 1, n_o, generator=g) * 2 - 1,
         "obs_jac": torch.randn(B, 1, n_o, ndx, generator=g), "xi": torch.rand(B, n_xi, generator=g) * 2 - 1,
         "jac": torch.randn(B, T_h, A, ndx, generator=g)}
    b["a_hist"] = b["tau0"][:, :1]
    return b, {"n_action": A, "n_obs": n_o, "n_xi": n_xi, "ndx": ndx}


def dataset_batch(path, B, T_h, seed=0):
    from sdp_cli.data.chunks import ChunkDataset, fit_normalizer, load_dataset

    arrays, _, task = load_dataset(path)
    ds = ChunkDataset(task, arrays, T_h)
    tens = ds.tensors(fit_normalizer(task, arrays, ds.action))
    idx = torch.randint(0, len(ds), (B,), generator=torch.Generator().manual_seed(seed))
    b = {k: v[idx] for k, v in tens.items()}
    return b, {"n_action": b["tau0"].shape[-1], "n_obs": b["obs"].shape[-1], "n_xi": b["xi"].shape[-1],
               "ndx": task.ndx}


def make_step(mode, batch, dims, T_h):
    method = "dp" if mode == "dp" else "sdp"
    sob_mode = "vjp" if mode == "sdp-vjp" else "jvp"
    cfg = TrainConfig.of(method=method, horizon=T_h, sobolev_mode=sob_mode,
                      sobolev_fraction=0.5 if mode == "sdp-jvp-half" else 1.0)
    torch.manual_seed(0)
    net = DiffusionUnetPolicy(cfg, dims)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    gen = torch.Generator().manual_seed(0)
    if mode == "sdp-jvp-func":   # the U-Net's tangent by torch.func.jvp instead of its hand-written pass
        unet = net.unet

        def func_jvp(tau, tau_d, k, cond, cond_d):
            return jvp(lambda t, c: unet.forward(t, k, c), (tau, cond),
                       (torch.zeros_like(tau) if tau_d is None else tau_d, cond_d))

        unet.forward_jvp = func_jvp

    def step():
        loss, _ = net.compute_loss(batch, gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
    return step, sum(p.numel() for p in net.parameters())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--horizon", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--data", default=None)
    ap.add_argument("--action-dim", type=int, default=1, help="A of the synthetic batch")
    ap.add_argument("--ndx", type=int, default=2, help="state tangent size of the synthetic batch")
    ap.add_argument("--n-obs", type=int, default=3, help="observation size (obs(x), u_prev) of the synthetic batch")
    ap.add_argument("--n-xi", type=int, default=2, help="xi size of the synthetic batch")
    ap.add_argument("--modes", default="dp,sdp-vjp,sdp-jvp-func,sdp-jvp,sdp-jvp-half")
    ap.add_argument("--csv", default=None, help="append the medians and ratios to this CSV")
    ap.add_argument("--setting", default="synthetic", help="name of this setting in the CSV")
    a = ap.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
    batch, dims = (dataset_batch(a.data, a.batch, a.horizon) if a.data else synthetic_batch(a.batch, a.horizon, a.action_dim, a.ndx, a.n_obs, a.n_xi))
    modes = a.modes.split(",")
    steps = {}
    for m in modes:
        steps[m], n_params = make_step(m, batch, dims, a.horizon)
        steps[m]()   # warm-up
    times = {m: [] for m in modes}
    cpu = {m: [] for m in modes}
    for _ in range(a.rounds):
        for m in modes:
            t, c = time.perf_counter(), time.process_time()
            steps[m]()
            times[m].append(time.perf_counter() - t)
            cpu[m].append(time.process_time() - c)
    print(f"B={a.batch} T_h={a.horizon} params={n_params} torch={torch.__version__} threads={torch.get_num_threads()} "
          f"cpus={os.cpu_count()} load={os.getloadavg()[0]:.1f} rounds={a.rounds}")
    ref = statistics.median(times["dp"]) if "dp" in times else None
    cref = statistics.median(cpu["dp"]) if "dp" in cpu else None
    rows = []
    for m in modes:
        med, lo, cmed = statistics.median(times[m]), min(times[m]), statistics.median(cpu[m])
        ratio = f"  ratio to dp {med / ref:.2f} (min-based {lo / min(times['dp']):.2f})" if ref else ""
        cratio = f"  ratio {cmed / cref:.2f}" if cref else ""
        print(f"{m:14s} wall: median {med:.3f} s  min {lo:.3f} s{ratio} | CPU time: median {cmed:.3f} s{cratio}")
        rows.append({"setting": a.setting, "mode": m, "batch": a.batch, "horizon": a.horizon,
                     "wall_median_s": med, "cpu_median_s": cmed,
                     "wall_ratio_to_dp": med / ref if ref else float("nan"),
                     "cpu_ratio_to_dp": cmed / cref if cref else float("nan"), "rounds": a.rounds,
                     "threads": torch.get_num_threads(), "load": round(os.getloadavg()[0], 1),
                     "torch": torch.__version__})
    if a.csv:
        write_csv(a.csv, a.setting, rows)


def write_csv(path: str, setting: str, rows: list[dict]) -> None:
    """Replace the rows of ``setting`` in the CSV at ``path`` (created if missing) by ``rows``."""
    import pandas as pd

    from sdp_cli.data.artifacts import atomic_write_bytes

    new = pd.DataFrame(rows)
    if os.path.exists(path):
        old = pd.read_csv(path)
        new = pd.concat([old[old.setting != setting], new], ignore_index=True)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    atomic_write_bytes(path, lambda f: new.to_csv(f, index=False, float_format="%.6g"))


if __name__ == "__main__":
    main()

"""``sdp plot-dataset``: the 3D paths of a dataset's trajectories with start, goal and obstacles.

What is drawn per trajectory (rows of ``X (N, T+1, nx)``): ``task.path_points(X)`` (T+1, 3)
when the task defines it (UR5: ``tool0`` positions; quadrotor: base positions), otherwise
the position of the model's last frame (the pendulums' tip). Start = first path point
(blue dot), goal = ``task.target(xi)`` or ``task.goal`` (red cross). Quadrotor columns are
drawn as translucent cylinders (true radius) between ``task.z_bounds``, with their
inflated radius (column + airframe, the constraint) as a dashed circle at the floor.
Left panel: 3D view; right panel: top view (x, y) of the same paths and columns.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from sdp_cli.data.artifacts import atomic_write_bytes, check_writable, load_npz
from sdp_cli.errors import SdpError
from sdp_cli.rules import Range, check_value
from sdp_cli.tasks import get_task

_FORMATS = {".png", ".pdf", ".svg", ".jpg", ".jpeg"}


def trajectory_points(task, X: np.ndarray) -> np.ndarray:
    """3D points of one trajectory: (T+1, nx) -> (T+1, 3) (:meth:`Task.path_points`)."""
    return np.asarray(task.path_points(X), dtype=float)


def goal_point(task, xi: np.ndarray) -> np.ndarray | None:
    """The goal position (3,) of instance ``xi``, if the task has one (:meth:`Task.goal_point`)."""
    g = task.goal_point(xi)
    return None if g is None else np.asarray(g, dtype=float)


def _draw_columns(ax, task, zlim) -> None:
    cols = np.asarray(task.columns).reshape(-1, 3)
    if not len(cols):
        return
    z0, z1 = zlim
    th = np.linspace(0, 2 * np.pi, 40)
    zz = np.array([z0, z1])
    r_quad = float(task.column_margin)
    for cx, cy, r in cols:
        TH, ZZ = np.meshgrid(th, zz)
        ax.plot_surface(cx + r * np.cos(TH), cy + r * np.sin(TH), ZZ, color="0.45", alpha=0.35,
                        linewidth=0, shade=False)
        if r_quad:
            R = r + r_quad
            ax.plot(cx + R * np.cos(th), cy + R * np.sin(th), np.full_like(th, z0), "--", color="0.5", lw=0.8)


def _draw_columns_top(ax, task) -> None:
    import matplotlib.patches as mpatches

    r_quad = float(task.column_margin)
    for k, (cx, cy, r) in enumerate(np.asarray(task.columns).reshape(-1, 3)):
        ax.add_patch(mpatches.Circle((cx, cy), r, color="0.45", alpha=0.5, lw=0, label="column" if k == 0 else None))
        if r_quad:
            ax.add_patch(mpatches.Circle((cx, cy), r + r_quad, fill=False, ls="--", color="0.5", lw=0.8,
                                         label=f"column + airframe radius {r_quad:g} m (the constraint on the "
                                               f"centre)" if k == 0 else None))


def plot_dataset(path: str | Path, out: str | Path, max_traj: int = 20, dpi: int = 120,
                 title: str | None = None) -> tuple[Path, int]:
    """Draw the dataset at ``path`` into the image ``out``; returns (path written, trajectories drawn)."""
    out = Path(out)
    if out.suffix.lower() not in _FORMATS:
        raise SdpError(f"--out must end with one of {', '.join(sorted(_FORMATS))}, got {out.name!r}")

    check_value("--max-traj", max_traj, Range(ge=1))
    check_value("--dpi", dpi, Range(ge=1, le=2400))   # beyond: matplotlib's image size limit for a figure
    check_writable(out)
    arrays, meta = load_npz(path, kind="dataset")

    if "task" not in meta or "X" not in arrays or "xi" not in arrays:
        raise SdpError(f"{path}: dataset without task name, X or xi")
    task = get_task(meta["task"], **(meta.get("task_options") or {}))
    X, XI = arrays["X"], arrays["xi"]
    if X.ndim != 3 or X.shape[2] != task.nx or len(XI) != len(X):
        raise SdpError(f"{path}: X of shape {X.shape} does not match task {task.name!r} (nx = {task.nx})")
    n = min(len(X), max_traj)
    if n == 0:
        raise SdpError(f"{path}: empty dataset, nothing to plot")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = [trajectory_points(task, X[i]) for i in range(n)]
    goals = [goal_point(task, XI[i]) for i in range(n)]
    pts = np.concatenate(paths + [g[None] for g in goals if g is not None])
    lo, hi = pts.min(0), pts.max(0)
    zlim = task.z_bounds
    if zlim is not None:
        lo[2], hi[2] = min(lo[2], zlim[0]), max(hi[2], zlim[1])

    fig = plt.figure(figsize=(12, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    top = fig.add_subplot(1, 2, 2)
    cmap = plt.get_cmap("viridis")
    for i, (P, g) in enumerate(zip(paths, goals)):
        c = cmap(i / max(n - 1, 1))
        ax.plot(P[:, 0], P[:, 1], P[:, 2], color=c, lw=1.2)
        top.plot(P[:, 0], P[:, 1], color=c, lw=1.2)
        ax.scatter(*P[0], color="tab:blue", s=18, depthshade=False, label="start" if i == 0 else None)
        top.scatter(*P[0, :2], color="tab:blue", s=18, zorder=3)
        if g is not None:
            ax.scatter(*g, color="tab:red", marker="x", s=30, depthshade=False, label="goal" if i == 0 else None)
            top.scatter(*g[:2], color="tab:red", marker="x", s=30, zorder=3)
    _draw_columns_top(top, task)
    if zlim is not None:
        _draw_columns(ax, task, zlim)
        cols = np.asarray(task.columns).reshape(-1, 3)
        if len(cols):
            lo[:2] = np.minimum(lo[:2], (cols[:, :2] - cols[:, 2:]).min(0))
            hi[:2] = np.maximum(hi[:2], (cols[:, :2] + cols[:, 2:]).max(0))
    if task.base_marker is not None:
        b = np.asarray(task.base_marker, dtype=float)
        lo, hi = np.minimum(lo, b), np.maximum(hi, b)     # the base is drawn inside the axes
        ax.scatter(*b, color="k", marker="s", s=30, depthshade=False, label="robot base")
        top.scatter(*b[:2], color="k", marker="s", s=30)
    span = np.maximum(hi - lo, 1e-3)
    pad = 0.05 * span.max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_zlim(lo[2] - pad, hi[2] + pad)
    ax.set_box_aspect(tuple(span + 2 * pad))
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):     # few ticks: no overlapping labels on short axes
        axis.set_major_locator(MaxNLocator(4))
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x [m]", labelpad=6)
    ax.set_ylabel("y [m]", labelpad=6)
    ax.set_zlabel("z [m]", labelpad=6)
    ax.legend(loc="upper left", fontsize=8)
    if top.get_legend_handles_labels()[0]:   # below the axes: the columns stay visible
        top.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=7, ncol=2, frameon=False)
    top.set_xlim(lo[0] - pad, hi[0] + pad)
    top.set_ylim(lo[1] - pad, hi[1] + pad)
    top.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view", fontsize=10)
    top.grid(alpha=0.3)
    fig.suptitle(title or f"{meta['task']}: {n} of {len(X)} trajectories ({Path(path).name})", fontsize=11)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.subplots_adjust(wspace=0.35)
    fig.savefig(buf, format=out.suffix.lower().lstrip(".").replace("jpg", "jpeg"), dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return atomic_write_bytes(out, lambda f: f.write(buf.getvalue())), n

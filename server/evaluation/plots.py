"""Pictures of results: the trajectory over the map, seen from above (the paper's Fig. 2)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def up_direction(poses: np.ndarray) -> np.ndarray:
    """World 'up' from camera poses (N, 4, 4) T_world_camera: a hand-held camera is held roughly
    upright with its y axis pointing down, though often pitched; world frames are usually
    gravity-aligned (or the first camera's), so the nearest world axis is taken."""
    mean_up = -poses[:, :3, 1].mean(axis=0)
    axis = int(np.argmax(np.abs(mean_up)))
    up = np.zeros(3)
    up[axis] = np.sign(mean_up[axis]) or 1.0
    return up


def top_view_basis(up: np.ndarray) -> np.ndarray:
    """Two horizontal unit axes (2, 3) perpendicular to ``up``."""
    helper = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a)])


def plot_top_view(
    path: str | Path,
    trajectories: dict[str, np.ndarray],
    map_points: np.ndarray | None = None,
    title: str = "",
) -> None:
    """Write a PNG: map points coloured by height (heat map) with trajectories on top.

    trajectories: name -> (N, 4, 4) T_world_camera; the first one sets 'up'.
    """
    first = next(iter(trajectories.values()))
    up = up_direction(first)
    basis = top_view_basis(up)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    if map_points is not None and len(map_points):
        pts = map_points
        if len(pts) > 200_000:
            pts = pts[np.random.default_rng(0).choice(len(pts), 200_000, replace=False)]
        height = pts @ up
        order = np.argsort(height)  # higher points drawn last, as seen from above
        xy = pts[order] @ basis.T
        sc = ax.scatter(
            xy[:, 0], xy[:, 1], c=height[order], s=0.3, cmap="jet", alpha=0.6, linewidths=0
        )
        fig.colorbar(sc, ax=ax, shrink=0.7, label="height (m)")
    styles = ["-", "--", "-.", ":"]
    colours = ["black", "tab:green", "tab:red", "tab:purple", "tab:orange"]
    for i, (name, poses) in enumerate(trajectories.items()):
        xy = poses[:, :3, 3] @ basis.T
        ax.plot(xy[:, 0], xy[:, 1], styles[i % 4], color=colours[i % 5], lw=1.8, label=name)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=colours[i % 5], ms=5)
    ax.set_aspect("equal")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.legend(loc="upper right")
    ax.set_title(title or "trajectory, top view")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

"""Top-down plots of a scene: room, furniture, objects, route, driven path (matplotlib, headless)."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def draw_world(ax, world, route=None) -> None:
    """Boxes of the static world (floor and ceiling left out) and the objects with their names."""
    for b in world.boxes:
        if b.name in ("floor", "ceiling"):
            continue
        corners = np.array([[sx, sy, 0] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))]) * b.half
        pts = corners @ b.T_world_box[:3, :3].T + b.T_world_box[:3, 3]
        is_obj = any(b.name == o.name for o in world.objects)
        ax.fill(pts[:, 0], pts[:, 1], color="tab:orange" if is_obj else "0.75", alpha=0.9 if is_obj else 0.6,
                lw=0.5, ec="0.3")
    for o in world.objects:
        x, y = o.T_world_obj[:2, 3]
        ax.annotate(o.name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7)
    if route is not None:
        wp = np.array([w[:2] for w in route.waypoints])
        ax.plot(wp[:, 0], wp[:, 1], "k--", lw=0.8, label="route")
        ax.plot(wp[:, 0], wp[:, 1], "kx", ms=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def save(fig, path) -> None:
    """The figure as a PNG, atomically (a temporary file, then renamed onto ``path``)."""
    from testbed.io import atomic_path

    try:
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png", metadata={"Software": None})
    finally:
        plt.close(fig)


def scene_figure(world, route, path_xy: np.ndarray | None = None, title: str = ""):
    fig, ax = plt.subplots(figsize=(8, 6))
    draw_world(ax, world, route)
    if path_xy is not None and len(path_xy):
        ax.plot(path_xy[:, 0], path_xy[:, 1], "b-", lw=1.2, label="driven path (ground truth)")
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=7)
    return fig, ax

"""PNG renderings of a world (segments by material, routes, start pose) and of a simulated scan in it.

For the blueprint image use ``Blueprint.save_png``. Uses matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from glassmap.sim.laser import SimScan
from glassmap.sim.materials import MaterialKind
from glassmap.sim.world import World

KIND_COLORS = {
    MaterialKind.WALL: "#303030",
    MaterialKind.GLASS: "#1f9bd6",
    MaterialKind.FRAME: "#8c6d31",
    MaterialKind.METAL: "#b000b0",
    MaterialKind.WHITEBOARD: "#2ca02c",
    MaterialKind.RETRO: "#ff7f0e",
    MaterialKind.DARK: "#7f7f7f",
    MaterialKind.OBJECT: "#a0522d",
}


def _figure(world: World, scale: float = 0.35, max_inches: float = 18.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (xmin, ymin), (xmax, ymax) = world.bounds
    w = min(max((xmax - xmin) * scale, 4.0), max_inches)
    h = min(max((ymax - ymin) * w / max(xmax - xmin, 1e-6), 3.0), max_inches)
    fig, ax = plt.subplots(figsize=(w, h + 0.8), dpi=110)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return fig, ax


def draw_world(ax, world: World, alpha: float = 1.0, legend: bool = True) -> None:
    """Draw the segments of ``world`` on a matplotlib axis, coloured by material kind."""
    from matplotlib.collections import LineCollection

    for kind, color in KIND_COLORS.items():
        sel = world.segment_kind == int(kind)
        if sel.any():
            ax.add_collection(LineCollection(world.segments[sel], colors=color, linewidths=1.6, alpha=alpha,
                                             label=kind.name.lower()))
    ax.autoscale()
    if legend:
        ax.legend(loc="upper right", fontsize=7, ncol=4)


def render_world(world: World, path: str | Path, routes: bool = True) -> Path:
    """Write a PNG of the world: segments by material, routes (dashed) and the start pose (arrow)."""
    import matplotlib.pyplot as plt

    fig, ax = _figure(world)
    draw_world(ax, world)
    if routes:
        for name, wp in world.routes.items():
            ax.plot(wp[:, 0], wp[:, 1], "--", lw=1, label=f"route {name}")
            ax.plot(wp[0, 0], wp[0, 1], "o", ms=4, color="k")
        x, y, yaw = world.start_pose
        ax.annotate("", xy=(x + 0.6 * np.cos(yaw), y + 0.6 * np.sin(yaw)), xytext=(x, y),
                    arrowprops=dict(arrowstyle="->", color="k"))
        ax.legend(loc="upper right", fontsize=7, ncol=4)
    ax.set_title(f"world {world.name}: {world.description}", fontsize=9)
    return _save(fig, plt, path)


def render_scan(world: World, scan: SimScan, path: str | Path, color_by: str = "material") -> Path:
    """Write a PNG of a scan in its world: end points coloured by the material hit (``material``) or by
    intensity (``intensity``), glass returns ringed, beams through glass drawn faintly."""
    import matplotlib.pyplot as plt

    if color_by not in ("material", "intensity"):
        raise ValueError(f"color_by must be 'material' or 'intensity', got {color_by!r}")
    fig, ax = _figure(world)
    draw_world(ax, world, alpha=0.35, legend=False)
    x, y, yaw = scan.laser_pose
    ang = yaw + scan.geometry.angles
    ok = np.isfinite(scan.ranges)
    px = x + scan.ranges[ok] * np.cos(ang[ok])
    py = y + scan.ranges[ok] * np.sin(ang[ok])
    through = scan.crossed_glass & ok
    for k in np.flatnonzero(through)[::4]:
        ax.plot([x, x + scan.ranges[k] * np.cos(ang[k])], [y, y + scan.ranges[k] * np.sin(ang[k])],
                color="#1f9bd6", lw=0.3, alpha=0.3)
    if color_by == "material":
        for kind, color in KIND_COLORS.items():
            sel = scan.material[ok] == int(kind)
            if sel.any():
                ax.plot(px[sel], py[sel], ".", ms=2.5, color=color, label=f"{kind.name.lower()} ({sel.sum()})")
    else:
        sc = ax.scatter(px, py, c=scan.intensities[ok], s=3, cmap="viridis")
        fig.colorbar(sc, ax=ax, label="intensity", shrink=0.7)
    g = scan.is_glass & ok
    ax.plot(x + scan.ranges[g] * np.cos(ang[g]), y + scan.ranges[g] * np.sin(ang[g]), "o", mfc="none",
            mec="#d62728", ms=5, label=f"glass returns ({g.sum()})")
    ax.plot([x], [y], "k^", ms=6)
    ax.legend(loc="upper right", fontsize=7, ncol=3)
    ax.set_title(f"scan in {world.name} at x={x:.2f} y={y:.2f} yaw={np.degrees(yaw):.0f} deg: "
                 f"{ok.sum()} returns, {np.isinf(scan.ranges).sum()} no return", fontsize=9)
    return _save(fig, plt, path)


def _save(fig, plt, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path

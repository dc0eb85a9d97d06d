"""Top-down scene maps (PNG): navigable floor, walls, doors, windows, labelled objects, coloured rooms.

matplotlib is imported here only (Agg backend), when a map is drawn.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sonicverse_core.errors import SceneFileError
from sonicverse_core.scene.model import Door, Scene, StructureKind

ROOM_COLOURS = {"living room": "#f6e7c8", "kitchen": "#fbd5c0", "bedroom": "#dce9f7", "bathroom": "#d4f0ec",
                "corridor": "#ececec"}


def draw_map(scene: Scene, out: str | Path, grid=None, paths: list[np.ndarray] | None = None,
             markers: dict[str, tuple] | None = None, title: str | None = None, dpi: int = 110,
             path_labels: list[str] | None = None) -> Path:
    """Write a top-down map of ``scene`` to ``out``; optional navgrid overlay, trajectories and markers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    out = Path(out)
    if not out.parent.exists():
        raise SceneFileError(f"output folder does not exist: {out.parent}")
    lo, hi = scene.bounds
    size = hi[:2] - lo[:2]
    fig, ax = plt.subplots(figsize=(min(16, 2 + size[0] * 0.7), min(14, 1.5 + size[1] * 0.7)))
    for r in scene.rooms:
        ax.add_patch(Polygon(r.footprint, closed=True, fc=ROOM_COLOURS.get(r.type, "#eeeeee"), ec="none", zorder=0))
        c = r.footprint.mean(0)
        ax.text(c[0], c[1], f"{r.name}\n{r.area:.1f} m²", ha="center", va="center", fontsize=8, color="#555",
                zorder=5, style="italic")
    if grid is not None:
        nav = np.where(grid.labels == grid.main_label, 1.0, np.nan)
        ext = (grid.origin[0], grid.origin[0] + grid.shape[1] * grid.config.cell,
               grid.origin[1], grid.origin[1] + grid.shape[0] * grid.config.cell)
        ax.imshow(nav, origin="lower", extent=ext, cmap="Greens", vmin=0, vmax=4, alpha=0.55, zorder=1,
                  interpolation="nearest")
    colours = {StructureKind.WALL: "#333333", StructureKind.WINDOW: "#3a8fd8", StructureKind.OTHER: "#777777"}
    for p in scene.static:
        if p.kind in (StructureKind.FLOOR, StructureKind.CEILING):
            continue
        b = p.mesh.bounds
        if p.kind != StructureKind.WINDOW and b[0, 2] > scene.floor_z + 0.5:
            continue  # lintels and wall above windows: keep door openings visible
        lw = 2.5 if p.kind == StructureKind.WINDOW else 0
        ax.add_patch(Polygon([(b[0, 0], b[0, 1]), (b[1, 0], b[0, 1]), (b[1, 0], b[1, 1]), (b[0, 0], b[1, 1])],
                             fc=colours.get(p.kind, "#333"), ec=colours.get(p.kind, "#333"), lw=lw,
                             zorder=3.5 if p.kind == StructureKind.WINDOW else 3))
    for o in scene.objects:
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
        blo, bhi = o.mesh.bounds
        loc = (blo[:2] + bhi[:2]) / 2 + corners * (bhi[:2] - blo[:2]) / 2
        world = loc @ o.pose[:2, :2].T + o.pose[:2, 3]
        if isinstance(o, Door):
            ax.add_patch(Polygon(world, fc="#a0522d", ec="#5a2d0c", lw=0.8, zorder=4))
            continue
        ax.add_patch(Polygon(world, fc="#c9b79c", ec="#6d5d45", lw=0.6, alpha=0.9, zorder=2))
        c = world.mean(0)
        ax.text(c[0], c[1], o.category.replace("_", " "), ha="center", va="center", fontsize=5.5, zorder=6)
    colours = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd")
    for k, path in enumerate(paths or []):
        label = path_labels[k] if path_labels and k < len(path_labels) else None
        ax.plot(path[:, 0], path[:, 1], "-", color=colours[k % len(colours)], lw=1.6, zorder=7, label=label)
    if path_labels:
        ax.legend(loc="upper right", fontsize=8)
    for label, (x, y, style) in (markers or {}).items():
        ax.plot([x], [y], style, ms=9, zorder=8)
        ax.annotate(label, (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8, zorder=8)
    ax.set_xlim(lo[0] - 0.3, hi[0] + 0.3)
    ax.set_ylim(lo[1] - 0.3, hi[1] + 0.3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or scene.spec, fontsize=10)
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=dpi)
    finally:
        plt.close(fig)
    return out

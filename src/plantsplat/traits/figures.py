"""The traits figure: a top view with the PCA axes and widths, a side view with the height.

Usage:
    traits_figure(result, "ws/plant_01/traits.png", title="plant_01")
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from plantsplat import traitdefs
from plantsplat.io import atomic_path

FIGURE_SIZE_IN = (13, 6.2)
"""Width and height of the figure (inches)."""
PANEL_WIDTH_RATIOS = (1, 1.15)
"""Widths of the top view and the side view, relative to each other."""
DPI = 110
"""Resolution of the PNG (dots per inch): 1430 x 682 pixels."""
POINT_SIZE = 1.5
"""Marker area of a plant point (points squared)."""
LINE_WIDTH = 1.5
"""Width of the ground line and of the counted fruits' circles (points)."""
MAX_CUBE_POINTS = 5000
"""The cube is drawn from at most this many of its points (a random subset)."""
LABEL_FONT_SIZE = 10
"""Font size of the widths' and the height's labels and of the title."""
LEGEND_FONT_SIZE = 8
"""Font size of the legends."""
GRID_ALPHA = 0.3
"""Opacity of the grid lines."""
LABEL_OFFSET = 0.06
"""A width's label sits beyond its arrow's end by this share of the arrow's length."""
LABEL_BOX = {"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5}
"""The white box behind a width's label."""
CENTRE_MARKER_SIZE = 12
"""Size of the cross at the PCA centre (points)."""
FRUIT_MARKER_SIZE = 160
"""Area of the circle around a counted fruit (points squared)."""
SIDE_MARGIN = 0.05
"""Side view: the margin left of the plant, and the height arrow's distance right of it, as shares of its width."""
SIDE_LABEL_ROOM = 0.3
"""Side view: room right of the plant for the height's label, as a share of its width."""


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def traits_figure(result, path: str | Path, title: str = "", max_points: int = 30000, quality: str | None = None
                  ) -> None:
    """Draw ``result`` (a :class:`~plantsplat.traits.result.TraitResult` with plant points) to a PNG; ``quality``:
    the verdict to print (default the measurement's own, before the stage's checks).

    Left: top view (x, y) of the plant's points in their colours, the cube's footprint, the PCA
    centre and axes and the width1/width2 extents as a rectangle. Right: side view (the points
    projected on the major axis vs z) with the ground line and the height.
    """
    matplotlib.use("Agg")
    P = result.plant_points  # [M, 3]
    if P is None or len(P) < 4:
        raise ValueError("the result has no plant points to draw")
    C = result.plant_colors
    idx = _subsample(len(P), max_points)
    col = (C[idx] / 255.0) if C is not None else "tab:green"
    centre, axes = traitdefs.pca_axes(P)  # [2], [2, 2]
    proj = (P[:, :2] - centre) @ axes.T  # [M, 2]
    lo, hi = proj.min(0), proj.max(0)
    t = result.traits

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=FIGURE_SIZE_IN, gridspec_kw={"width_ratios": PANEL_WIDTH_RATIOS})
    # top view
    ax1.scatter(P[idx, 0], P[idx, 1], s=POINT_SIZE, c=col, linewidths=0)
    if result.cube_points is not None and len(result.cube_points):
        cq = result.cube_points[_subsample(len(result.cube_points), MAX_CUBE_POINTS)]
        ax1.scatter(cq[:, 0], cq[:, 1], s=1, c="0.6", linewidths=0, label="cube")
    rect = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [lo[0], lo[1]]])
    rect_xy = centre + rect @ axes  # [5, 2]
    ax1.plot(rect_xy[:, 0], rect_xy[:, 1], "k--", lw=1)
    for i, (name, colr) in enumerate((("width 1", "tab:red"), ("width 2", "tab:blue"))):
        a = np.zeros(2)
        b = np.zeros(2)
        a[i], b[i] = lo[i], hi[i]
        # the arrow runs through the PCA centre along its axis
        pa, pb = centre + a @ axes, centre + b @ axes
        ax1.annotate("", xy=pb, xytext=pa, arrowprops={"arrowstyle": "<->", "color": colr, "lw": 2})
        val = t.get("width1_cm" if i == 0 else "width2_cm")
        ax1.text(*(pb + LABEL_OFFSET * (pb - pa)), f"{name}\n{val:.1f} cm" if val is not None else name, color=colr,
                 fontsize=LABEL_FONT_SIZE, ha="center", va="center", fontweight="bold", bbox=LABEL_BOX)
    ax1.plot(*centre, "k+", ms=CENTRE_MARKER_SIZE)
    fc = result.fruit_centres
    if fc is not None and len(fc):
        ax1.scatter(fc[:, 0], fc[:, 1], s=FRUIT_MARKER_SIZE, facecolors="none", edgecolors="m", linewidths=LINE_WIDTH,
                    label=f"counted fruit ({len(fc)})")
        ax1.legend(loc="lower right", fontsize=LEGEND_FONT_SIZE)
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (cm)")
    ax1.set_ylabel("y (cm)")
    ax1.set_title("top view: PCA axes of the ground-projected points")
    ax1.grid(alpha=GRID_ALPHA)
    # side view: along the major axis
    s_major = proj[:, 0]
    ax2.scatter(s_major[idx], P[idx, 2], s=POINT_SIZE, c=col, linewidths=0)
    zmax = P[:, 2].max()
    zmin = P[:, 2].min() if result.soil_z is None else result.soil_z
    ax2.axhline(0.0, color="0.3", lw=LINE_WIDTH, label="ground (z = 0)")
    ax2.axhline(zmin, color="tab:purple", ls="--", lw=1, label=None if result.soil_z is None else "soil")
    ax2.axhline(zmax, color="tab:purple", ls="--", lw=1)
    xa = hi[0] + SIDE_MARGIN * (hi[0] - lo[0])
    ax2.annotate("", xy=(xa, zmax), xytext=(xa, zmin), arrowprops={"arrowstyle": "<->", "color": "tab:purple", "lw": 2})
    h = t.get("height_cm")
    ax2.text(xa, (zmin + zmax) / 2, f" height\n {h:.1f} cm" if h is not None else " height", color="tab:purple",
             fontsize=LABEL_FONT_SIZE, va="center", fontweight="bold")
    ax2.set_xlim(lo[0] - SIDE_MARGIN * (hi[0] - lo[0]), hi[0] + SIDE_LABEL_ROOM * (hi[0] - lo[0]))
    ax2.set_aspect("equal")
    ax2.set_xlabel("along width 1 (cm)")
    ax2.set_ylabel("z (cm)")
    ax2.set_title("side view")
    ax2.legend(loc="upper left", fontsize=LEGEND_FONT_SIZE)
    ax2.grid(alpha=GRID_ALPHA)
    lines = [
        f"{title}  quality: {quality or result.quality}  scale: {result.scale.get('source')}",
        "  ".join(
            f"{k}={t[k]:.1f}" if isinstance(t.get(k), float) else f"{k}={t.get(k)}"
            for k in ("canopy_volume_cm3", "canopy_area_cm2", "fruit_count")
        ),
    ]
    fig.suptitle("\n".join(lines), fontsize=LABEL_FONT_SIZE)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)

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


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def traits_figure(result, path: str | Path, title: str = "", max_points: int = 30000) -> None:
    """Draw ``result`` (a :class:`~plantsplat.traits.result.TraitResult` with plant points) to a PNG.

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

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 6.2), gridspec_kw={"width_ratios": [1, 1.15]})
    # top view
    ax1.scatter(P[idx, 0], P[idx, 1], s=1.5, c=col, linewidths=0)
    if result.cube_points is not None and len(result.cube_points):
        cq = result.cube_points[_subsample(len(result.cube_points), 5000)]
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
        ax1.text(*(pb + 0.06 * (pb - pa)), f"{name}\n{val:.1f} cm" if val is not None else name, color=colr,
                 fontsize=10, ha="center", va="center", fontweight="bold",
                 bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5})
    ax1.plot(*centre, "k+", ms=12)
    fc = result.fruit_centres
    if fc is not None and len(fc):
        ax1.scatter(fc[:, 0], fc[:, 1], s=160, facecolors="none", edgecolors="m", linewidths=1.5,
                    label=f"counted fruit ({len(fc)})")
        ax1.legend(loc="lower right", fontsize=8)
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (cm)")
    ax1.set_ylabel("y (cm)")
    ax1.set_title("top view: PCA axes of the ground-projected points")
    ax1.grid(alpha=0.3)
    # side view: along the major axis
    s_major = proj[:, 0]
    ax2.scatter(s_major[idx], P[idx, 2], s=1.5, c=col, linewidths=0)
    zmax = P[:, 2].max()
    zmin = P[:, 2].min() if result.soil_z is None else result.soil_z
    ax2.axhline(0.0, color="0.3", lw=1.5, label="ground (z = 0)")
    ax2.axhline(zmin, color="tab:purple", ls="--", lw=1, label=None if result.soil_z is None else "soil")
    ax2.axhline(zmax, color="tab:purple", ls="--", lw=1)
    xa = hi[0] + 0.05 * (hi[0] - lo[0])
    ax2.annotate("", xy=(xa, zmax), xytext=(xa, zmin), arrowprops={"arrowstyle": "<->", "color": "tab:purple", "lw": 2})
    h = t.get("height_cm")
    ax2.text(xa, (zmin + zmax) / 2, f" height\n {h:.1f} cm" if h is not None else " height", color="tab:purple",
             fontsize=10, va="center", fontweight="bold")
    ax2.set_xlim(lo[0] - 0.05 * (hi[0] - lo[0]), hi[0] + 0.3 * (hi[0] - lo[0]))
    ax2.set_aspect("equal")
    ax2.set_xlabel("along width 1 (cm)")
    ax2.set_ylabel("z (cm)")
    ax2.set_title("side view")
    ax2.legend(loc="upper left", fontsize=8)
    ax2.grid(alpha=0.3)
    lines = [
        f"{title}  quality: {result.quality}  scale: {result.scale.get('source')}",
        "  ".join(
            f"{k}={t[k]:.1f}" if isinstance(t.get(k), float) else f"{k}={t.get(k)}"
            for k in ("canopy_volume_cm3", "canopy_area_cm2", "fruit_count")
        ),
    ]
    fig.suptitle("\n".join(lines), fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)

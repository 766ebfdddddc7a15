"""A picture of the 3D decision: the quick model's Gaussians coloured by what the segment stage called them.

Top view (x, y) and side view (x, z) of the opaque Gaussians near the orbit's axis: plant, pot and soil, the
calibration cube, the room, and the candidates the evidence set aside. A user sees at a glance whether a patch
of wall, the table or the soil was taken for plant, before trusting the masks and the traits.

Usage:
    decision_figure(obj, "ws/plant01/segment_decision.png")  # obj: plantsplat.segment.object3d.ObjectModel
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch

from plantsplat.io import atomic_path
from plantsplat.segment.object3d import PART_NAMES

PART_COLOURS = {"room": "#b0b0b0", "plant": "#1a9e3a", "pot": "#8c5a2b", "cube": "#2a5fd6", "set aside": "#e0341e"}
"""Colour of each part in the figure."""
PART_SIZES = {"room": 1.0, "plant": 2.0, "pot": 1.5, "cube": 1.5, "set aside": 6.0}
"""Marker size of each part (what was set aside is drawn large, to be found)."""
SHOWN_OPACITY = 0.5
"""Only Gaussians at least this opaque are drawn (the surfaces, not the haze)."""
MAX_POINTS = 40_000
"""At most this many Gaussians are drawn (a seeded even sample of them)."""
DPI = 100
MARGIN = 0.15
"""Margin around the decided object, as a share of its largest extent."""


def decision_figure(obj, path: str | Path, max_points: int = MAX_POINTS) -> None:
    """Draw the decision of ``obj`` (an :class:`~plantsplat.segment.object3d.ObjectModel` with ``part``) to a PNG."""
    matplotlib.use("Agg")
    mu = _upright(obj)  # [N, 3]: across, across, up
    opaque = torch.sigmoid(obj.params["opacities"]).numpy().reshape(-1) >= SHOWN_OPACITY
    near = np.linalg.norm(mu[:, :2], axis=1) < float(obj.info.get("reach", np.inf))
    shown = np.flatnonzero(opaque & near)
    if len(shown) > max_points:
        shown = np.sort(np.random.default_rng(0).choice(shown, max_points, replace=False))
    part = obj.part[shown]
    lo, hi = _frame(mu[shown[part != PART_NAMES.index("room")]])
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    for ax, (a, b, label) in zip(axes, ((0, 1, "from above"), (0, 2, "from the side"))):
        for k, name in enumerate(PART_NAMES):  # room first, what was set aside last (on top)
            m = part == k
            if m.any():
                ax.scatter(mu[shown[m], a], mu[shown[m], b], s=PART_SIZES[name], c=PART_COLOURS[name], linewidths=0,
                           label=f"{name} ({int((obj.part == k).sum()):,})")
        if lo is not None:
            ax.set_xlim(lo[a], hi[a])
            ax.set_ylim(lo[b], hi[b])
        ax.set_aspect("equal")
        ax.set_title(label)
        ax.set_xlabel("cm, from the orbit's axis" if obj.cube is not None else "model units, from the orbit's axis")
    axes[0].legend(loc="upper right", fontsize=8, markerscale=3)
    fig.suptitle("The 3D decision: the quick model's opaque Gaussians near the orbit's axis, by what they were "
                 "called (counts: all Gaussians)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)


def _frame(points: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Axis limits ``(lo [3], hi [3])`` around the decided object ``points`` ``[N, 3]`` (plant, pot, cube, what was
    set aside), with a margin of :data:`MARGIN` of their extent; far room points fall outside. ``(None, None)``
    without any: the plot's own limits."""
    if len(points) == 0:
        return None, None
    lo, hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
    pad = MARGIN * float(np.max(hi - lo))
    return lo - pad, hi + pad


def _upright(obj) -> np.ndarray:
    """The quick model's Gaussian centres ``[N, 3]`` in a frame on the orbit's axis with its third axis up: the cube
    frame's axes, moved onto the axis, heights from the ground, when the model is calibrated; else two directions
    across the axis the cameras circle and up along it, from the point the cameras look at."""
    mu = obj.params["means"].numpy().astype(np.float64)
    up = np.asarray(obj.up, np.float64) / np.linalg.norm(obj.up)
    axis = np.asarray(obj.axis, np.float64)
    if obj.cube is not None:  # heights from the ground the cube stands on
        origin, basis = np.r_[axis[:2], 0.0], np.eye(3)
    else:
        across = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        across /= np.linalg.norm(across)
        origin, basis = axis, np.stack([across, np.cross(up, across), up])  # rows: across, across, up
    return (mu - origin) @ basis.T

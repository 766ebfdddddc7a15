"""Trait definitions shared by the synthetic ground truth and the measurement stage.

These are the paper's definitions (see ``ARCHITECTURE.md``), written once so that the ground truth
of ``plantsplat synth`` and the estimates of ``plantsplat traits`` mean exactly the same thing.
All inputs are plant points only (leaves, petioles, crown, fruit, flowers; no pot, soil or cube) in
a gravity-aligned frame (z up), in centimetres.

Height is measured from the soil, as a ruler standing on the soil measures it: fruit hanging over the
pot's rim does not change it. The paper's height, the z extent of all plant points, is kept as
``height_extent_cm``; with no soil known (no pot) both are the extent.

Example:
    >>> import numpy as np
    >>> pts = np.array([[0, 0, 0], [4, 0, 1], [0, 2, 3], [4, 2, 2.0]])
    >>> round(plant_height(pts), 3), round(plant_height(pts, soil_z=0.5), 3), [round(w, 3) for w in pca_widths(pts)]
    (3.0, 2.5, [4.0, 2.0])
"""

from __future__ import annotations

import numpy as np

TRAIT_KEYS = ("height_cm", "height_extent_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2",
              "fruit_count")
"""The keys shared by ``ground_truth.json`` and ``traits.json``. ``fruit_count`` counts ripe (red)
fruit, the ones a colour model can tell from leaves; synthetic captures also give ``fruit_count_all``."""

TRAIT_LABELS = {
    "height_cm": "height from the soil",
    "height_extent_cm": "height extent",
    "width1_cm": "width 1 (major axis)",
    "width2_cm": "width 2 (minor axis)",
    "canopy_volume_cm3": "canopy volume",
    "canopy_area_cm2": "canopy area",
    "fruit_count": "fruit count",
}
"""How each trait is named for people (tables, reports, figures)."""
TRAIT_UNITS = {"height_cm": "cm", "height_extent_cm": "cm", "width1_cm": "cm", "width2_cm": "cm",
               "canopy_volume_cm3": "cm³", "canopy_area_cm2": "cm²", "fruit_count": ""}
"""Each trait's unit."""


def _check(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {pts.shape}")
    if len(pts) < 4:
        raise ValueError(f"need at least 4 plant points, got {len(pts)}")
    return pts


def plant_height(points: np.ndarray, trim: float = 0.0, soil_z: float | None = None) -> float:
    """Height: max z above the soil at ``soil_z``, or max z minus min z without one (the extent). ``trim`` > 0 uses
    the trim and 1-trim quantiles instead of the extremes."""
    z = _check(points)[:, 2]
    lo, hi = np.quantile(z, [trim, 1.0 - trim]) if trim > 0 else (z.min(), z.max())
    return float(hi - (lo if soil_z is None else soil_z))


def pca_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PCA of the ground-projected points: ``(centre [2], axes [2, 2])``, rows = major, minor axis."""
    xy = _check(points)[:, :2]
    centre = xy.mean(axis=0)
    cov = np.cov((xy - centre).T)
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1]
    axes = evecs[:, order].T
    # a deterministic sign: each axis points to +x (or +y when perpendicular to x)
    for i in range(2):
        ref = axes[i, 0] if abs(axes[i, 0]) > 1e-12 else axes[i, 1]
        if ref < 0:
            axes[i] = -axes[i]
    return centre, axes


def pca_widths(points: np.ndarray, trim: float = 0.0) -> tuple[float, float]:
    """Width 1 and width 2: extents of the ground-projected points along the major / minor PCA axes."""
    pts = _check(points)
    centre, axes = pca_axes(pts)
    proj = (pts[:, :2] - centre) @ axes.T  # [N, 2]
    if trim > 0:
        lo, hi = np.quantile(proj, [trim, 1.0 - trim], axis=0)
    else:
        lo, hi = proj.min(axis=0), proj.max(axis=0)
    ext = hi - lo
    return float(ext[0]), float(ext[1])


def canopy_volume(points: np.ndarray) -> float:
    """Canopy volume: volume of the 3D convex hull of the plant points (cm^3); 0 for points in one plane."""
    return _hull_measure(_check(points))


def canopy_area(points: np.ndarray) -> float:
    """Projected canopy area: area of the 2D convex hull of the ground-projected points (cm^2); 0 for points on one
    line."""
    return _hull_measure(_check(points)[:, :2])  # in 2D, the hull's volume is its area


def _hull_measure(points: np.ndarray) -> float:
    """The volume (3D) or area (2D) of the points' convex hull; 0 where they do not span the space (Qhull refuses a
    flat hull: a cloud exported flat, or a single leaf seen edge-on)."""
    from scipy.spatial import ConvexHull, QhullError  # deferred: SciPy is slow to load, and the CLI imports this module

    try:
        return float(ConvexHull(points).volume)
    except QhullError:
        return 0.0


def geometric_traits(points: np.ndarray, trim: float = 0.0, soil_z: float | None = None) -> dict[str, float]:
    """All point-based traits (everything but the fruit count) under their shared names; height from ``soil_z``."""
    w1, w2 = pca_widths(points, trim)
    return {
        "height_cm": plant_height(points, trim, soil_z),
        "height_extent_cm": plant_height(points, trim),
        "width1_cm": w1,
        "width2_cm": w2,
        "canopy_volume_cm3": canopy_volume(points),
        "canopy_area_cm2": canopy_area(points),
    }

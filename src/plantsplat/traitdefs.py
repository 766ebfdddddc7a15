"""Trait definitions shared by the synthetic ground truth and the measurement stage.

These are the paper's definitions (see ``ARCHITECTURE.md``), written once so that the ground truth
of ``plantsplat synth`` and the estimates of ``plantsplat traits`` mean exactly the same thing.
All inputs are plant points only (leaves, petioles, crown, fruit, flowers; no pot, soil or cube) in
a gravity-aligned frame (z up), in centimetres.

Example:
    >>> import numpy as np
    >>> pts = np.array([[0, 0, 0], [4, 0, 1], [0, 2, 3], [4, 2, 2.0]])
    >>> round(plant_height(pts), 3), [round(w, 3) for w in pca_widths(pts)]
    (3.0, [4.0, 2.0])
"""

from __future__ import annotations

import numpy as np

TRAIT_KEYS = ("height_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2", "fruit_count")
"""The keys shared by ``ground_truth.json`` and ``traits.json``. ``fruit_count`` counts ripe (red)
fruit, the ones a colour model can tell from leaves; synthetic captures also give ``fruit_count_all``."""


def _check(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {pts.shape}")
    if len(pts) < 4:
        raise ValueError(f"need at least 4 plant points, got {len(pts)}")
    return pts


def plant_height(points: np.ndarray, trim: float = 0.0) -> float:
    """Height: max z minus min z (``trim`` > 0 uses the trim and 1-trim quantiles instead)."""
    z = _check(points)[:, 2]
    if trim > 0:
        lo, hi = np.quantile(z, [trim, 1.0 - trim])
        return float(hi - lo)
    return float(z.max() - z.min())


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
    """Canopy volume: volume of the 3D convex hull of the plant points (cm^3)."""
    from scipy.spatial import ConvexHull

    return float(ConvexHull(_check(points)).volume)


def canopy_area(points: np.ndarray) -> float:
    """Projected canopy area: area of the 2D convex hull of the ground-projected points (cm^2)."""
    from scipy.spatial import ConvexHull

    return float(ConvexHull(_check(points)[:, :2]).volume)  # in 2D, .volume is the area


def geometric_traits(points: np.ndarray, trim: float = 0.0) -> dict[str, float]:
    """All point-based traits (everything but the fruit count) under their shared names."""
    w1, w2 = pca_widths(points, trim)
    return {
        "height_cm": plant_height(points, trim),
        "width1_cm": w1,
        "width2_cm": w2,
        "canopy_volume_cm3": canopy_volume(points),
        "canopy_area_cm2": canopy_area(points),
    }

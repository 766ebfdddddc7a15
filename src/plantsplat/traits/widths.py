"""The widths' bounds: how far the crown's PCA axes can turn when the same surface is sampled another way.

Width 1 and width 2 are extents along the principal axes of the plant's ground-projected points
(:func:`plantsplat.traitdefs.pca_widths`). Those axes are fixed by the points' covariance, and so by how
the surface is sampled: a model's Gaussians crowd where the texture is fine, a mesh's vertices where its
modeller put them, an even sample of the surface spreads over its area. On an elongated crown every
sampling gives the same axes; on a nearly round one the covariance is nearly isotropic and a change of
sampling turns them by tens of degrees (synthetic demo seed 404, 2026-11-27: the true cloud's
covariance is isotropic to 1 %, ours turned 67 degrees from it, and width 1 came out 25 % wide while the
extent along every direction agreed with the truth's within 3 %).

The axes' sensitivity is measured on the cloud itself. Write the covariance's anisotropy as the vector
``a = (Cxx - Cyy, 2 Cxy)``: its length is the gap between the two eigenvalues and its angle twice the
major axis's. The cloud's points and an even resample of them (one per cell of a ``cell_cm`` grid: the
surface by its area) give two such vectors; a perturbation as large as their difference ``d`` turns
the axis by at most ``asin(|d| / |a|) / 2``, and by any angle once ``|d|`` reaches ``|a|``. The widths'
bounds are the extents along every axis within that angle of the measured one, widened by two
standard errors of the scale (as the height's, :mod:`plantsplat.traits.height`).

Example:
    >>> rng = np.random.default_rng(0)
    >>> long = rng.uniform([-20, -5, 0], [20, 5, 1], (4000, 3))  # a crown four times longer than wide
    >>> turn = axis_turn_deg(long, cell_cm=0.5)
    >>> turn < 2.0
    True
    >>> b = width_bounds(long, turn, scale_se=0.0)
    >>> [round(v) for v in b[0]], [round(v) for v in b[1]]
    ([40, 40], [10, 11])
"""

from __future__ import annotations

import numpy as np

from plantsplat.traitdefs import pca_axes


def anisotropy(points: np.ndarray) -> np.ndarray:
    """``(Cxx - Cyy, 2 Cxy)`` of the ground-projected ``points`` ``[N, 3]``: its length is the gap between the
    covariance's eigenvalues, its angle twice the major axis's. ``[2]``"""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    c = xy.T @ xy / len(xy)
    return np.array([c[0, 0] - c[1, 1], 2.0 * c[0, 1]])


def even_sample(points: np.ndarray, cell_cm: float) -> np.ndarray:
    """One point per occupied cell of a ``cell_cm`` grid (the first in the cloud's order): the surface sampled by its
    area, whatever crowded the cloud's points. ``[M, 3]``"""
    keys = np.floor(points / cell_cm).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def axis_turn_deg(points: np.ndarray, cell_cm: float) -> float:
    """How far (degrees, 0-90) the PCA axes of ``points`` ``[N, 3]`` (cm) can turn under a change of sampling as large
    as the one between the points and their even resample (see the module docstring)."""
    a = anisotropy(points)
    d = np.linalg.norm(a - anisotropy(even_sample(points, cell_cm)))
    gap = float(np.linalg.norm(a))
    if d >= gap:
        return 90.0
    return float(np.degrees(0.5 * np.arcsin(d / gap)))


def width_bounds(points: np.ndarray, turn_deg: float, scale_se: float | None, step_deg: float = 1.0
                 ) -> tuple[tuple[float, float], tuple[float, float]]:
    """``((w1_low, w1_high), (w2_low, w2_high))`` (cm): the extents of ``points`` ``[N, 3]`` along the PCA axes turned
    by up to ``turn_deg`` either way (every ``step_deg``), each end widened by two standard errors (``scale_se``, a
    fraction) of the scale."""
    centre, axes = pca_axes(points)
    xy = points[:, :2] - centre
    base = np.arctan2(axes[0, 1], axes[0, 0])
    half = np.append(np.arange(0.0, turn_deg, step_deg), turn_deg)  # 0 (the widths themselves) to the full turn
    turns = np.radians(np.concatenate([-half[:0:-1], half]))
    ext = np.empty((len(turns), 2))
    for i, t in enumerate(base + turns):
        u = np.array([np.cos(t), np.sin(t)])
        p, q = xy @ u, xy @ np.array([-u[1], u[0]])
        ext[i] = p.max() - p.min(), q.max() - q.min()
    k = 2.0 * (scale_se or 0.0)
    return ((float(ext[:, 0].min() * (1 - k)), float(ext[:, 0].max() * (1 + k))),
            (float(ext[:, 1].min() * (1 - k)), float(ext[:, 1].max() * (1 + k))))

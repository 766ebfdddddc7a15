"""The soil surface in a pot from the poses stage's SfM points: the lowest layer in the pot as dense as a surface.

Structure from motion triangulates a point only where several frames see the same texture, and puts it
at the depth those frames agree on. Soil is textured, so wherever it shows between the leaves (from the
high ring of cameras, looking down into the pot) its points gather in one thin horizontal layer; the
quick scene model, fitted to the images alone, draws the same soil as a layer 1-1.5 cm thick at grazing
angles (2026-11-27: on foreign render 110 its layer began at the rim, 1.9 cm above the true soil, while
the SfM points inside the pot peaked within 0.15 cm of it; the same held on all twelve benchmark captures,
among them one whose soil the quick model did not see at all).

Inside the pot (within ``inside_radius`` of its axis, below the rim), the points are counted in windows
one ``slab`` thick, stepped by a quarter of it. Nothing of the plant grows below the soil, and what SfM
puts under it (a few points seen through gaps, matched wrongly) is sparse. The soil is the lowest window of at
least ``min_points`` points, followed up while the next window holds as many, to the layer's peak; its height is the
median of the peak window's points. (On eleven benchmark captures, 2026-11-28, the lowest such window began 0.5-1.0
cm under the true soil, on the lower flank of its layer, and the peak lay within 0.11 cm of the truth.)
How dense the leaves and the crown above it are says nothing of the soil: on foreign render 110 a window of
leaves by the rim holds twice the points of the soil's few visible patches, and a rule that asked the soil for
half the densest window's points found no soil there (this one finds it within 0.03 cm). A surface filling the
pot spreads over its inside (the RMS distance of its points from the axis is 0.71 of the inside's radius for an
even layer; 0.60-0.79 on the twelve captures), while what stands on the soil where the leaves hide it, the crown
and the petioles' feet, gathers near the axis:
a lowest layer that spreads less than ``spread`` is not the soil, and the soil was not seen. Nor is a layer that
holds fewer points than lie under it: what lies under the soil is sparse, so a window that only climbs out of an
even scatter of points (the soil seen at grazing angles over the rim, its points spread over a centimetre and a
half, and the crown's points above them) has no surface in it (synthetic demo seed 732, 2026-11-30: 21 points in
the window found 0.7 cm above the true soil, 34 under it; on 22 other captures, own, demo and foreign, 0.63-0.96 of
the points from the window down lay in it).

Example:
    >>> rng = np.random.default_rng(0)
    >>> soil = np.c_[rng.uniform(-4, 4, (300, 2)), rng.normal(10.0, 0.05, 300)]  # the soil, 10 cm up
    >>> leaves = np.c_[rng.uniform(-4, 4, (400, 2)), rng.uniform(10.5, 14.0, 400)]  # leaves above it
    >>> noise = np.c_[rng.uniform(-4, 4, (10, 2)), rng.uniform(6.0, 9.5, 10)]  # stray points under it
    >>> layer = soil_layer(np.concatenate([soil, leaves, noise]), np.zeros(2), inside_radius=4.8, rim_z=13.0, slab=0.5,
    ...                    depth=6.0)
    >>> round(layer.z, 1), layer.points > 250
    (10.0, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LAYER_SPREAD = 0.5
"""The soil's layer spreads over the pot's inside: its points' RMS distance from the axis is at least this share of
the inside's radius."""
STEPS_PER_SLAB = 4
"""The windows are stepped by this fraction of their thickness."""
MIN_LAYER_POINTS = 10
"""A window of fewer SfM points than this is not a surface (the soil was not seen)."""


@dataclass(frozen=True)
class SoilLayer:
    """The soil found among the SfM points: its height ``z`` (cm), how many points lie in its layer and their RMS
    distance from ``z`` (cm)."""

    z: float
    points: int
    thickness: float = 0.0


def soil_layer(points: np.ndarray, centre: np.ndarray, inside_radius: float, rim_z: float, slab: float, depth: float,
               spread: float = LAYER_SPREAD, min_points: int = MIN_LAYER_POINTS) -> SoilLayer | None:
    """The soil in a pot (axis at ``centre`` ``[2]``, its inside reaching ``inside_radius`` from the axis, the rim at
    ``rim_z``; cm) from SfM ``points`` ``[N, 3]`` in the cube frame: the lowest window ``slab`` cm thick, within
    ``depth`` below the rim, holding at least ``min_points``, followed up to the layer's peak, its points spread from
    the axis by at least ``spread`` of ``inside_radius`` (see the module docstring); None when there is no such
    window."""
    d = np.linalg.norm(points[:, :2] - np.asarray(centre, float), axis=1)
    keep = (d < inside_radius) & (points[:, 2] < rim_z) & (points[:, 2] >= rim_z - depth)
    order = np.argsort(points[keep, 2], kind="stable")
    z, r = points[keep, 2][order], d[keep][order]
    if len(z) < min_points:
        return None
    starts = np.arange(rim_z - depth, rim_z - slab + 1e-9, slab / STEPS_PER_SLAB)
    counts = np.searchsorted(z, starts + slab) - np.searchsorted(z, starts)  # [W] points in each window
    dense = np.flatnonzero(counts >= min_points)
    if not len(dense):
        return None
    peak = int(dense[0])
    while peak + 1 < len(counts) and counts[peak + 1] >= counts[peak]:  # up the layer to its peak
        peak += 1
    lo = starts[peak]
    inside = (z >= lo) & (z < lo + slab)
    if np.sqrt(np.mean(r[inside] ** 2)) < spread * inside_radius:
        return None  # the crown and the petioles' feet, standing on a soil no frame saw
    if inside.sum() <= (z < lo).sum():
        return None  # no surface stands out of the scatter under it
    height = float(np.median(z[inside]))
    return SoilLayer(z=height, points=int(inside.sum()), thickness=float(np.sqrt(np.mean((z[inside] - height) ** 2))))

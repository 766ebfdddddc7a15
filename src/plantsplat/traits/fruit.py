"""Fruit: the colour models, the fruit count, and fruit hanging apart from the plant joining it.

Fruit colour model (documented, not tuned to a scene): a point is fruit-coloured when its HSV hue is
within ``fruit_hue_deg`` of pure red, its saturation is at least ``fruit_min_saturation`` and its
value at least ``fruit_min_value`` (ripe strawberries; unripe white/green fruit are not counted).
Fruit-coloured plant points are clustered with DBSCAN (radius ``fruit_eps_cm``); clusters with at
least ``fruit_min_points`` points and an extent of at least ``fruit_min_size_cm`` are the pieces of
fruit. Touching fruit merge into one cluster and are counted once; pieces of one fruit that the frames
show as one red region are joined by the traits stage (:mod:`plantsplat.traits.fruit_views`).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import open3d as o3d
from matplotlib.colors import rgb_to_hsv
from scipy.spatial import cKDTree

from plantsplat.traits.config import TraitsConfig

FULL_TURN_DEG = 360.0
"""Degrees in a full turn of the hue circle (red at 0 and at the full turn)."""


def fruit_mask(colors: np.ndarray, s: TraitsConfig) -> np.ndarray:
    """[N] bool: points whose colour matches the fruit colour model (see the module docstring).

    Example:
        >>> fruit_mask(np.array([[200, 20, 30], [40, 160, 50], [250, 250, 250]], np.uint8), TraitsConfig()).tolist()
        [True, False, False]
    """
    hsv = rgb_to_hsv(np.asarray(colors, dtype=np.float64).reshape(-1, 3) / 255.0)  # [N, 3] in 0..1
    hue_deg = hsv[:, 0] * FULL_TURN_DEG
    red = np.minimum(hue_deg, FULL_TURN_DEG - hue_deg) <= s.fruit_hue_deg
    return red & (hsv[:, 1] >= s.fruit_min_saturation) & (hsv[:, 2] >= s.fruit_min_value)


UNRIPE_HSV = ((18, 35, 60), (45, 150, 255))
"""Unripe fruit colours, OpenCV HSV (hue 0-179) box: pale yellow-green to cream, not too grey or too saturated."""


def unripe_fruit_mask(colors: np.ndarray) -> np.ndarray:
    """[N] bool: points of unripe-fruit colour (:data:`UNRIPE_HSV`). Beige walls and boxes share it: the traits
    stage uses it only for fruit-sized clusters hanging beside the plant.

    Example:
        >>> unripe_fruit_mask(np.array([[190, 196, 140], [40, 160, 50], [200, 20, 30]], np.uint8)).tolist()
        [True, False, False]
    """
    hsv = cv2.cvtColor(np.ascontiguousarray(np.asarray(colors, np.uint8).reshape(1, -1, 3)), cv2.COLOR_RGB2HSV)[0]
    lo, hi = (np.array(b, np.uint8) for b in UNRIPE_HSV)
    return np.all((hsv >= lo) & (hsv <= hi), axis=1)


def fruit_sized(points: np.ndarray, max_cm: float) -> bool:
    """Whether a cluster ``[N, 3]`` (cm) is no thicker than a fruit: its middle extent along its principal axes at
    most ``max_cm`` and its longest at most twice that (fruit hanging side by side make a longer piece, not a
    thicker one; a slab of wall or a box is wider).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> fruit_sized(rng.uniform(-1, 1, (500, 3)) * [1.5, 1.5, 4], 7.0), fruit_sized(rng.uniform(-5, 5, (500, 3)), 7.0)
        (True, False)
    """
    c = np.asarray(points, np.float64) - np.mean(points, axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    ext = np.sort(np.ptp(c @ vt.T, axis=0))[::-1]  # longest first
    return bool(ext[1] <= max_cm and ext[0] <= 2.0 * max_cm)


def fruit_pieces(points_cm: np.ndarray, colors: np.ndarray, s: TraitsConfig, core_points: int = 5) -> list[np.ndarray]:
    """The fruit-coloured points grouped by DBSCAN (radius ``s.fruit_eps_cm``, ``core_points`` neighbours make a
    core point): each group ``[N, 3]`` of at least ``s.fruit_min_points`` points and ``s.fruit_min_size_cm`` extent."""
    m = fruit_mask(colors, s)
    if m.sum() < s.fruit_min_points:
        return []
    fp = points_cm[m]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(fp))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        lab = np.asarray(pc.cluster_dbscan(eps=s.fruit_eps_cm, min_points=core_points), dtype=np.int64)
    pieces = [fp[lab == i] for i in range(lab.max() + 1)]
    return [q for q in pieces if len(q) >= s.fruit_min_points and np.max(q.max(0) - q.min(0)) >= s.fruit_min_size_cm]


def count_fruit(points_cm: np.ndarray, colors: np.ndarray, s: TraitsConfig, core_points: int = 5,
                same_fruit: Callable[[list[np.ndarray]], list[int]] | None = None) -> tuple[int, np.ndarray]:
    """Count fruit among the plant's points: ``(count, centres [F, 3])``. The pieces of :func:`fruit_pieces` are
    fruit; ``same_fruit`` (pieces -> group of each) may join pieces of one fruit
    (:func:`plantsplat.traits.fruit_views.judge_by_views`)."""
    pieces = fruit_pieces(points_cm, colors, s, core_points)
    groups = same_fruit(pieces) if same_fruit is not None and len(pieces) > 1 else list(range(len(pieces)))
    centres = [np.concatenate([q for q, g in zip(pieces, groups) if g == k]).mean(0) for k in dict.fromkeys(groups)]
    return len(centres), np.array(centres).reshape(-1, 3)


def is_hanging_fruit(q, cols_q, s: TraitsConfig, top: float) -> bool:
    """Whether a cluster ``q [N, 3]`` (colours ``cols_q``) is a fruit (mostly red, or fruit-sized and mostly red or
    unripe-coloured) no higher than the plant's ``top``."""
    red = fruit_mask(cols_q, s)
    fruit = red.mean() >= s.fruit_join_fraction or (
        s.fruit_join_unripe_cm > 0 and fruit_sized(q, s.fruit_join_unripe_cm)
        and (red | unripe_fruit_mask(cols_q)).mean() >= s.fruit_join_fraction)
    return bool(fruit) and q[:, 2].max() <= top


def join_fruit(pts_cm, cols, labels, sel, s: TraitsConfig, notes: list[str]) -> list:
    """Fruit-coloured clusters left out as far from the plant but hanging within ``s.fruit_join_cm`` of
    it join the plant (fruit on peduncles too thin to reconstruct). Updates ``sel`` in place."""
    tree = cKDTree(pts_cm[sel.mask])
    top = float(pts_cm[sel.mask, 2].max())
    joined = []
    for e in sel.excluded:
        if e["reason"] != "far from the plant":
            continue
        m = labels == e["label"]
        q = pts_cm[m]
        if not is_hanging_fruit(q, cols[m], s, top):
            continue
        d, _ = tree.query(q, k=1, distance_upper_bound=s.fruit_join_cm)
        if np.isfinite(d).any():
            joined.append(e["label"])
    if joined:
        sel.mask = sel.mask | np.isin(labels, joined)
        sel.excluded[:] = [e for e in sel.excluded if e["label"] not in joined]
        sel.clusters.extend(joined)
        notes.append(f"{len(joined)} fruit-coloured cluster(s) (red or unripe) hanging within {s.fruit_join_cm:g} cm "
                     "of the plant joined it (fruit on peduncles too thin to reconstruct)")
    return joined

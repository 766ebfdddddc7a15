"""DBSCAN clustering of an exported Gaussian point cloud and selection of the plant's clusters.

The paper segments the exported cloud with DBSCAN (Ester et al. 1996). Here the clustering is
Open3D's ``cluster_dbscan``; its neighbourhood radius ``eps`` comes from the data:

* calibrated clouds (cm): ``eps = clip(eps_factor * median k-NN distance, eps_min_cm, eps_max_cm)``,
  so a dense cloud gets a tight radius and a sparse one still connects, within sane metric bounds;
* uncalibrated clouds (arbitrary units): ``eps = eps_factor * median k-NN distance``.

Large clouds are clustered on a random subset of at most ``max_points`` points; every other point
takes the label of its nearest clustered point when it lies within ``eps`` of it (noise otherwise).

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> a = rng.normal(0, 0.3, (500, 3)); b = rng.normal(0, 0.3, (300, 3)) + [10, 0, 0]
    >>> labels, eps = dbscan(np.concatenate([a, b]), calibrated=True)
    >>> sorted(np.bincount(labels[labels >= 0]).tolist())
    [300, 500]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from plantsplat.log import get_logger

log = get_logger(__name__)


def knn_spacing(points: np.ndarray, k: int = 8, sample: int = 5000, seed: int = 0) -> float:
    """Median distance from a point to its ``k``-th nearest neighbour (on a sample of the points).

    Example:
        >>> g = np.stack(np.meshgrid(*[np.arange(10.0)] * 3), -1).reshape(-1, 3)
        >>> knn_spacing(g, k=1)
        1.0
    """
    pts = np.asarray(points, dtype=np.float64)  # [N, 3]
    if len(pts) <= k:
        raise ValueError(f"need more than {k} points to measure the point spacing, got {len(pts)}")
    tree = cKDTree(pts)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(pts), size=min(sample, len(pts)), replace=False)
    d, _ = tree.query(pts[idx], k=k + 1)  # [S, k+1], column 0 is the point itself
    return float(np.median(d[:, k]))


def choose_eps(
    points: np.ndarray,
    calibrated: bool,
    min_points: int = 10,
    eps_factor: float = 3.0,
    eps_min_cm: float = 0.4,
    eps_max_cm: float = 2.0,
) -> float:
    """The DBSCAN radius for this cloud (see the module docstring)."""
    spacing = knn_spacing(points, k=min(min_points, len(points) - 1))
    eps = eps_factor * spacing
    if calibrated:
        eps = float(np.clip(eps, eps_min_cm, eps_max_cm))
    return float(eps)


def dbscan(
    points: np.ndarray,
    *,
    calibrated: bool,
    eps: float | None = None,
    min_points: int = 10,
    max_points: int = 250_000,
    seed: int = 0,
    eps_reference: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Cluster ``points [N, 3]`` with Open3D's DBSCAN. Returns ``(labels [N] int, eps)``; -1 is noise.

    Labels are renumbered by decreasing cluster size (0 = largest). ``eps_reference`` (``[M, 3]``,
    default ``points``) is the cloud whose point spacing sets the automatic radius (the Gaussian
    centres when ``points`` also holds extent samples).
    """
    pts = np.asarray(points, dtype=np.float64)  # [N, 3]
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        sub = np.sort(rng.choice(len(pts), size=max_points, replace=False))
    else:
        sub = np.arange(len(pts))
    if eps is None:
        # the radius follows the spacing of the points DBSCAN actually sees (the subset, if any)
        ref = pts if eps_reference is None else np.asarray(eps_reference, dtype=np.float64)
        frac = len(sub) / len(pts)
        if frac < 1:
            ref = ref[rng.choice(len(ref), size=max(min_points + 2, int(len(ref) * frac)), replace=False)]
        eps = choose_eps(ref, calibrated, min_points)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sub]))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        lab_sub = np.asarray(pc.cluster_dbscan(eps=float(eps), min_points=int(min_points)), dtype=np.int64)
    labels = np.full(len(pts), -1, dtype=np.int64)
    labels[sub] = lab_sub
    if len(sub) < len(pts):
        rest = np.setdiff1d(np.arange(len(pts)), sub)
        d, j = cKDTree(pts[sub]).query(pts[rest], k=1, distance_upper_bound=eps)
        ok = np.isfinite(d)
        labels[rest[ok]] = lab_sub[j[ok]]
    # renumber by size, largest first
    valid = labels >= 0
    if valid.any():
        counts = np.bincount(labels[valid])
        order = np.argsort(-counts, kind="stable")
        remap = np.empty_like(order)
        remap[order] = np.arange(len(order))
        labels[valid] = remap[labels[valid]]
    return labels, float(eps)


def far_clusters_reason(excluded: list[dict], plant_points: int, share: float = 0.05) -> str | None:
    """The warning for clusters left out as far from the plant that hold more than ``share`` (5 %) of
    ``plant_points``, or None.

    Example:
        >>> far_clusters_reason([{"label": 3, "points": 900, "reason": "far from the plant"}], 10000)
        '1 large cluster(s) left out as too far from the plant (900 points): check the plant is not split'
    """
    big = [e for e in excluded if e["reason"] == "far from the plant" and e["points"] > share * plant_points]
    if not big:
        return None
    return (f"{len(big)} large cluster(s) left out as too far from the plant "
            f"({', '.join(str(e['points']) for e in big)} points): check the plant is not split")


@dataclass
class PlantSelection:
    """Which clusters make up the plant."""

    mask: np.ndarray
    """[N] bool: points of the plant."""
    clusters: list[int]
    """Cluster labels merged into the plant (the main one first)."""
    main_fraction: float
    """Fraction of the plant's points in the main cluster."""
    excluded: list[dict]
    """Clusters left out (label, points, reason)."""
    reasons: list[str]
    """Quality warnings about a fragmented plant (large clusters left out: :func:`far_clusters_reason`, once the
    caller has joined what belongs to the plant, such as hanging fruit)."""


def _linked_groups(pts, labels, pieces: list[int], sizes: dict[int, int], merge_distance: float | None):
    """``root(label)``: the group of each piece, pieces linked by gaps of at most ``merge_distance`` (single
    linkage); one group for all without a distance."""
    group = {i: pieces[0] if merge_distance is None else i for i in pieces}

    def root(i):
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    if merge_distance is None:
        return root
    trees = {i: cKDTree(pts[labels == i]) for i in pieces}
    for a_idx, a in enumerate(pieces):
        for b in pieces[a_idx + 1:]:
            if root(a) == root(b):
                continue
            small, big = (a, b) if sizes[a] <= sizes[b] else (b, a)
            d, _ = trees[big].query(trees[small].data, k=1, distance_upper_bound=merge_distance)
            if np.isfinite(d).any():
                group[root(a)] = root(b)
    return root


def select_plant(
    points: np.ndarray,
    labels: np.ndarray,
    *,
    exclude: set[int] = frozenset(),
    merge_distance: float | None,
    min_cluster_fraction: float = 0.002,
    min_cluster_points: int = 10,
    max_pieces: int = 12,
    min_main_share: float = 0.25,
) -> PlantSelection | None:
    """The plant: every cluster that is not excluded (the cube) nor a floater (fewer points than
    ``min_cluster_fraction`` of the largest cluster's). With a ``merge_distance``, only the group of
    clusters linked by gaps of at most that distance (separated leaves, fruit on thin peduncles) that
    holds the most points. Returns None when no cluster is left. With a ``merge_distance``, a plant of more than
    ``max_pieces`` clusters, or whose largest cluster holds less than ``min_main_share`` of its points, is flagged as
    fragmented.

    Example:
        >>> rng = np.random.default_rng(1)
        >>> body = rng.normal(0, 2, (2000, 3)); leaf = rng.normal(0, 0.3, (200, 3)) + [9, 0, 0]
        >>> far = rng.normal(0, 0.3, (200, 3)) + [60, 0, 0]
        >>> pts = np.concatenate([body, leaf, far])
        >>> lab = np.r_[np.zeros(2000, int), np.ones(200, int), np.full(200, 2)]
        >>> sel = select_plant(pts, lab, merge_distance=5.0)
        >>> sel.clusters, int(sel.mask.sum())
        ([0, 1], 2200)
    """
    pts = np.asarray(points, dtype=np.float64)
    labels = np.asarray(labels)
    ids = [int(i) for i in np.unique(labels) if i >= 0 and int(i) not in exclude]
    if not ids:
        return None
    sizes = {i: int((labels == i).sum()) for i in ids}
    largest = max(ids, key=lambda i: sizes[i])
    min_size = max(min_cluster_points, int(np.ceil(min_cluster_fraction * sizes[largest])))
    excluded: list[dict] = []
    pieces = []
    for i in ids:
        if sizes[i] < min_size:
            excluded.append({"label": i, "points": sizes[i], "reason": "floater (too small)"})
        else:
            pieces.append(i)
    if not pieces:
        return None
    # the plant is the group with the most points: a fragmented plant outweighs one large piece of something else
    root = _linked_groups(pts, labels, pieces, sizes, merge_distance)
    totals: dict[int, int] = {}
    for i in pieces:
        totals[root(i)] = totals.get(root(i), 0) + sizes[i]
    best = max(totals, key=lambda r: (totals[r], r == root(largest)))
    chosen = sorted((i for i in pieces if root(i) == best), key=lambda i: -sizes[i])
    main = chosen[0]
    pending = [i for i in pieces if root(i) != best]
    for i in pending:
        excluded.append({"label": i, "points": sizes[i], "reason": "far from the plant"})
    mask = np.isin(labels, chosen)
    total = int(mask.sum())
    main_fraction = sizes[main] / total
    reasons: list[str] = []
    if merge_distance is not None:  # (without one every piece is plant by design: their number says nothing)
        if len(chosen) > max_pieces:
            reasons.append(f"plant assembled from {len(chosen)} clusters (more than {max_pieces}): "
                           "reconstruction is fragmented")
        if main_fraction < min_main_share:
            reasons.append(f"largest plant cluster holds only {main_fraction:.0%} of the plant's points: "
                           "reconstruction is fragmented")
    return PlantSelection(mask=mask, clusters=chosen, main_fraction=float(main_fraction), excluded=excluded, reasons=reasons)

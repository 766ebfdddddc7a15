"""Plant traits from a point cloud: cluster, find and measure the cube, select the plant, measure.

The library entry point is :func:`measure_traits` (any point cloud, calibrated or not); the CLI
stage's is :func:`traits_workspace` (reads ``WS/export/splat.ply``, the Gaussians with their extents
sampled, or ``WS/export/points.ply``, their centres; writes ``WS/traits.json``, ``traits.csv`` and
``traits.png``).

Steps (the paper's section 2.4, with the additions the issue asks for):

1. DBSCAN clustering (:mod:`plantsplat.traits.cluster`), radius from the data.
2. The cube: the cluster whose oriented bounding box looks like a cube; its edge from the distances
   between its opposite faces' fitted planes (:mod:`plantsplat.traits.cube_fit`), or for Gaussian
   reconstructions from its points' envelope along the planes' axes (their faces' Gaussians fill the
   inside of the faces, so the planes lie inside).
3. Scale and frame. *Calibrated* clouds (the poses stage's ArUco calibration: cm, z up, origin under
   the cube) keep their frame; the cube planes cross-check the scale (their disagreement is reported)
   and the vertical. *Uncalibrated* clouds are scaled by ``10 cm / l_hat`` and moved into the cube's
   frame: z along the cube's up axis, origin at the centre of its bottom face (on the ground).
4. The plant: the largest non-cube cluster plus the clusters near it (separated leaves); floaters,
   clusters far away and clusters below the ground are left out.
5. Traits with the shared definitions of :mod:`plantsplat.traitdefs` (height, PCA widths, convex
   hull volume, projected canopy area), trimmed ("robust") height and widths, and a fruit count.

Fruit colour model (documented, not tuned to a scene): a point is fruit-coloured when its HSV hue is
within ``fruit_hue_deg`` of pure red, its saturation is at least ``fruit_min_saturation`` and its
value at least ``fruit_min_value`` (ripe strawberries; unripe white/green fruit are not counted).
Fruit-coloured plant points are clustered with DBSCAN (radius ``fruit_eps_cm``); clusters with at
least ``fruit_min_points`` points and an extent of at least ``fruit_min_size_cm`` count as fruit.
Touching fruit merge into one cluster and are counted once.

Example:
    >>> import numpy as np
    >>> from plantsplat.traits.cube_fit import cube_surface_points
    >>> rng = np.random.default_rng(0)
    >>> cube = cube_surface_points(10.0, 6000, rng, faces=("+x", "-x", "+y", "-y", "top"))
    >>> plant = rng.uniform([-8, -6, 5], [8, 6, 20], (20000, 3)) + [25, 0, 0]
    >>> res = measure_traits(np.concatenate([cube, plant]), None, calibrated=True)
    >>> res.quality, round(res.traits["height_cm"], 1)
    ('ok', 15.0)
"""

from __future__ import annotations

import csv
import io
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from plantsplat import traitdefs
from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError
from plantsplat.io import csv_cell
from plantsplat.log import get_logger
from plantsplat.traits.checks import soil_level

log = get_logger(__name__)

ROBUST_KEYS = ("height_cm", "height_extent_cm", "width1_cm", "width2_cm")


@dataclass
class TraitsConfig:
    """Settings of the trait measurement (all lengths in cm unless said otherwise)."""

    opacity_min: float = 0.1
    """Keep Gaussians whose opacity is at least this (the paper's culling threshold tau_alpha)."""
    max_scale_cm: float | None = None
    """Drop Gaussians whose largest extent exceeds this (cm; calibrated clouds only). None: keep all."""
    eps: float | None = None
    """DBSCAN radius in the cloud's units (cm when calibrated). None: from the point spacing."""
    eps_factor: float = 3.0
    """Automatic radius = this times the median distance to the min_points-th neighbour."""
    eps_min_cm: float = 0.4
    """Lower bound of the automatic radius on calibrated clouds (cm)."""
    eps_max_cm: float = 2.0
    """Upper bound of the automatic radius on calibrated clouds (cm)."""
    min_points: int = 10
    """DBSCAN minimum neighbourhood size."""
    max_cluster_points: int = 250_000
    """Cluster at most this many points (a random subset; the rest take their neighbour's label)."""
    merge_distance_cm: float | None = None
    """None: every cluster that is not the cube, below the ground or a floater is plant (the masks decided the
    object in 3D, so what the model holds is plant; leaves on petioles too thin to reconstruct are apart from
    the crown). A distance (cm): only the clusters linked to the plant by gaps up to it (for clouds made
    without such masks)."""
    min_cluster_fraction: float = 0.002
    """Clusters smaller than this fraction of the main plant cluster are floaters."""
    fruit_join_cm: float = 15.0
    """Clusters left out as far from the plant join it when they are mostly fruit-coloured, lie within this distance
    of the plant and no higher than its top: fruit hang on peduncles too thin to be reconstructed."""
    fruit_join_fraction: float = 0.5
    """Share of fruit-coloured points that makes a cluster a hanging fruit."""
    fruit_join_unripe_cm: float = 7.0
    """Unripe fruit and trusses of ripe and unripe fruit join the same way: clusters mostly of red or unripe-fruit
    colour (pale yellow-green to cream, the segmenter's colour model) no thicker than this (cm) and no longer than
    twice it (the segmenter's ``unripe_fruit_cm``), since walls, boxes and pots share the unripe colour; 0: only
    mostly red clusters join."""
    trim: float = 0.0005
    """Robust height/widths use the trim .. 1-trim quantiles instead of min .. max (0.0005: the ~0.05 % most
    extreme points on each side are ignored)."""
    cube_size_cm: float | None = None
    """Edge of the calibration cube (cm). Default: the cube the poses stage measured with (its record in
    markers.json, from --poses.cube-size), else the cube's default (:class:`~plantsplat.cube.CubeSpec`)."""
    scale_tolerance_pct: float = 3.0
    """Flag the result when ArUco and cube-plane scales disagree by more than this (%)."""
    max_tilt_deg: float = 3.0
    """Flag the result when the cube's vertical and the frame's z differ by more than this (deg)."""
    fruit_hue_deg: float = 12.0
    """Fruit colour: hue within this many degrees of red."""
    fruit_min_saturation: float = 0.45
    """Fruit colour: minimum HSV saturation (0..1)."""
    fruit_min_value: float = 0.2
    """Fruit colour: minimum HSV value (0..1)."""
    fruit_eps_cm: float = 0.6
    """DBSCAN radius for grouping fruit-coloured points into fruit (cm)."""
    fruit_min_points: int = 15
    """Minimum points of one fruit."""
    fruit_min_size_cm: float = 0.8
    """Minimum extent of one fruit (cm)."""
    extent_sigma: float = 2.0
    """0: measure the Gaussians' centres (the paper). > 0: also use the 6 ends of each Gaussian's principal
    axes at this many standard deviations (read from export/splat.ply), so that the Gaussians' extents count:
    a reconstruction's Gaussians sit inside the surfaces they draw, so their centres underestimate every trait."""
    cube_edge: Literal["auto", "planes", "envelope"] = "auto"
    """How the cube's edge is measured: 'planes' (mean distance between opposite faces' fitted planes: exact on
    surface samples), 'envelope' (the 1 %..99 % extent of the cube's points along its axes: Gaussian
    reconstructions, whose faces' planes lie inside the faces) or 'auto' (envelope for Gaussians, that is when
    opacities or extent samples come with the points; planes otherwise)."""
    seed: int = 0
    """Random seed (subsampling, RANSAC)."""


@dataclass
class TraitResult:
    """What :func:`measure_traits` found. ``traits`` holds None where a value could not be trusted."""

    traits: dict[str, float | int | None]
    robust: dict[str, float | None]
    quality: str
    """'ok', 'warning' (values given, see reasons) or 'failed' (no values)."""
    reasons: list[str]
    scale: dict
    cube: dict | None
    clusters: dict
    settings: dict
    plant_points: np.ndarray | None = None
    """[M, 3] the plant's points in the calibrated frame (cm, z up)."""
    plant_colors: np.ndarray | None = None
    """[M, 3] uint8 or None."""
    cube_points: np.ndarray | None = None
    """[K, 3] the cube's points in the calibrated frame."""
    fruit_centres: np.ndarray | None = None
    """[F, 3] centres of the counted fruit."""
    transform: np.ndarray | None = None
    """[4, 4] cloud -> calibrated frame (similarity)."""
    timings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """Informational messages that do not lower the quality."""
    soil_z: float | None = None
    """Height of the soil surface the height is measured from (cm, calibrated frame); None: the plant's extent."""

    def to_json(self) -> dict:
        """The ``traits.json`` content (without the point arrays)."""
        out: dict = {k: self.traits.get(k) for k in traitdefs.TRAIT_KEYS}
        out.update(
            {
                "units": traitdefs.TRAIT_UNITS,
                "quality": self.quality,
                "quality_reasons": self.reasons,
                "scale_source": self.scale.get("source"),
                "soil_z_cm": self.soil_z,
                "notes": self.notes,
                "robust": {k: self.robust.get(k) for k in ROBUST_KEYS} | {"trim": self.settings.get("trim")},
                "method": (
                    "DBSCAN (Open3D) clustering; cube = cluster with a cube-like oriented bounding box, axes from "
                    "RANSAC+least-squares planes of its faces, edge from the distance between opposite planes or, "
                    "for Gaussians, the 1-99 % envelope along the axes (scale.cube_edge_method); points = Gaussian "
                    "centres plus their axis ends at settings.extent_sigma; plant = largest other cluster plus nearby "
                    "clusters; height = top above the soil (soil_z_cm; the z extent without a soil), height_extent = z "
                    "extent, widths = extents along the PCA axes of the ground-projected points, "
                    "canopy volume/area = 3D/2D convex hull, fruit = clusters of red points"
                ),
                "scale": self.scale,
                "cube": self.cube,
                "clusters": self.clusters,
                "fruit_count_definition": "ripe (red) fruit: clusters of plant points whose colour is within "
                f"{self.settings.get('fruit_hue_deg')} deg of red hue, saturation >= "
                f"{self.settings.get('fruit_min_saturation')}, value >= {self.settings.get('fruit_min_value')}; "
                "unripe (white/green) fruit are not counted",
                "fruit_centres_cm": None if self.fruit_centres is None else np.round(self.fruit_centres, 3).tolist(),
                "transform_to_cm": None if self.transform is None else self.transform.tolist(),
                "settings": self.settings,
                "timings_s": self.timings,
            }
        )
        return out


def fruit_mask(colors: np.ndarray, s: TraitsConfig) -> np.ndarray:
    """[N] bool: points whose colour matches the fruit colour model (see the module docstring).

    Example:
        >>> fruit_mask(np.array([[200, 20, 30], [40, 160, 50], [250, 250, 250]], np.uint8), TraitsConfig()).tolist()
        [True, False, False]
    """
    from matplotlib.colors import rgb_to_hsv

    hsv = rgb_to_hsv(np.asarray(colors, dtype=np.float64).reshape(-1, 3) / 255.0)  # [N, 3] in 0..1
    hue_deg = hsv[:, 0] * 360.0
    red = np.minimum(hue_deg, 360.0 - hue_deg) <= s.fruit_hue_deg
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
    import cv2

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


def count_fruit(points_cm: np.ndarray, colors: np.ndarray, s: TraitsConfig) -> tuple[int, np.ndarray]:
    """Count fruit among the plant's points: ``(count, centres [F, 3])``."""
    import open3d as o3d

    m = fruit_mask(colors, s)
    if m.sum() < s.fruit_min_points:
        return 0, np.zeros((0, 3))
    fp = points_cm[m]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(fp))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        lab = np.asarray(pc.cluster_dbscan(eps=s.fruit_eps_cm, min_points=5), dtype=np.int64)
    centres = []
    for i in range(lab.max() + 1):
        q = fp[lab == i]
        if len(q) < s.fruit_min_points:
            continue
        if np.max(q.max(0) - q.min(0)) < s.fruit_min_size_cm:
            continue
        centres.append(q.mean(0))
    return len(centres), np.array(centres).reshape(-1, 3)


def _failed(reason: str, settings: TraitsConfig, scale: dict | None = None, **kw) -> TraitResult:
    return TraitResult(
        traits={k: None for k in traitdefs.TRAIT_KEYS},
        robust={k: None for k in ROBUST_KEYS},
        quality="failed",
        reasons=[reason],
        scale=scale or {"source": None},
        cube=kw.pop("cube", None),
        clusters=kw.pop("clusters", {}),
        settings=asdict(settings),
        **kw,
    )


def _filter_cloud(points, colors, opacity, scales, centre_mask, s: TraitsConfig, calibrated: bool):
    """The finite points that pass the opacity and Gaussian-size filters, with their colours."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {pts.shape}")
    cols = None if colors is None else np.asarray(colors)
    if cols is not None and cols.shape != pts.shape:
        raise ValueError(f"colors must have shape {pts.shape}, got {cols.shape}")
    keep = np.all(np.isfinite(pts), axis=1)
    n_in = len(pts)
    n_nonfinite = int((~keep).sum())
    if opacity is not None:
        keep &= np.asarray(opacity).reshape(-1) >= s.opacity_min
    if scales is not None and s.max_scale_cm is not None and calibrated:
        keep &= np.asarray(scales).reshape(len(pts), -1).max(1) <= s.max_scale_cm
    pts = pts[keep]
    cols = None if cols is None else cols[keep].astype(np.uint8)
    is_centre = np.ones(len(pts), bool) if centre_mask is None else np.asarray(centre_mask, bool)[keep]
    filt = {"input_points": n_in, "non_finite": n_nonfinite, "kept_points": int(len(pts))}
    return pts, cols, is_centre, filt


def _cluster_and_find_cube(pts, is_centre, centre_mask, s: TraitsConfig, calibrated: bool, size: float,
                           notes: list[str]):
    """DBSCAN clusters and the cube's cluster among them (clustered again tighter when the cube touches
    another cluster). Returns ``(labels, eps, first_eps, cube_label, candidates)``."""
    from plantsplat.traits.cluster import dbscan
    from plantsplat.traits.cube_fit import find_cube_cluster

    labels, eps = dbscan(pts, calibrated=calibrated, eps=s.eps, min_points=s.min_points,
                         max_points=s.max_cluster_points, seed=s.seed,
                         eps_reference=None if centre_mask is None else pts[is_centre])
    n_clusters = int(labels.max() + 1)
    log.info("DBSCAN: %d clusters, %d noise points (eps %.3g)", n_clusters, int((labels < 0).sum()), eps)
    cube_label, cands = find_cube_cluster(pts, labels, size if calibrated else None)
    first_eps = eps
    if cube_label is None and n_clusters > 0:
        # the cube may touch the plant or the ground remnants: split with a tighter radius once
        labels2, eps2 = dbscan(pts, calibrated=calibrated, eps=eps / 2, min_points=s.min_points,
                               max_points=s.max_cluster_points, seed=s.seed)
        lab2, cands2 = find_cube_cluster(pts, labels2, size if calibrated else None)
        if lab2 is not None:
            labels, eps, cube_label, cands = labels2, eps2, lab2, cands2
            notes.append(f"the cube touched another cluster; clustered again with half the radius ({eps2:.3g})")
    return labels, eps, first_eps, cube_label, cands


def _fit_cube(cube_pts, s: TraitsConfig, calibrated: bool, size: float, splats: bool, reasons: list[str]):
    """Fit the cube's faces to its cluster; the edge is taken from the planes or from the Gaussians'
    envelope (``s.cube_edge``). Returns ``(fit or None, edge_method)``."""
    from plantsplat.traits.cube_fit import fit_cube_planes, use_envelope

    if s.cube_edge not in ("auto", "planes", "envelope"):
        raise ValueError(f"cube_edge must be 'auto', 'planes' or 'envelope', got {s.cube_edge!r}")
    envelope = s.cube_edge == "envelope" or (s.cube_edge == "auto" and splats)
    edge_method = "envelope" if envelope else "planes"
    if cube_pts is None:
        return None, edge_method
    cube_fit = fit_cube_planes(cube_pts, size_hint=size if calibrated else None, seed=s.seed)
    if cube_fit is None:
        reasons.append("the cube cluster was found but no pair of opposite faces could be fitted")
    elif envelope:
        use_envelope(cube_fit, cube_pts)
    return cube_fit, edge_method


def _aruco_scale(cube_fit, size: float, edge_method: str, s: TraitsConfig, reasons: list[str]) -> dict:
    """The scale of a calibrated cloud, cross-checked against the cube found in it."""
    from plantsplat.traits.cube_fit import decide_up

    scale: dict = {"source": "aruco", "scale": 1.0}
    if cube_fit is None:
        reasons.append("no cube found in the cloud: the ArUco scale could not be cross-checked")
        return scale
    decide_up(cube_fit, reference_up=np.array([0.0, 0.0, 1.0]))
    edge_cm = cube_fit.edge
    planes_cm = cube_fit.extra.get("edge_planes", edge_cm)
    dis = (edge_cm / size - 1.0) * 100.0
    tilt = float(np.degrees(np.arccos(np.clip(abs(cube_fit.up[2]), -1, 1))))
    scale.update({"cube_edge_cm": edge_cm, "cube_edge_method": edge_method, "aruco_vs_cube_pct": dis,
                  "cube_edge_cm_planes": planes_cm, "planes_scale": size / planes_cm,
                  "aruco_vs_planes_pct": (planes_cm / size - 1.0) * 100.0, "cube_tilt_deg": tilt,
                  "cube_bottom_z_cm": float(cube_fit.bottom_centre[2])})
    if abs(dis) > s.scale_tolerance_pct:
        reasons.append(f"the cube measures {edge_cm:.2f} cm by its {edge_method}, {dis:+.1f} % off the ArUco "
                       f"scale (tolerance {s.scale_tolerance_pct} %): check the calibration")
    if tilt > s.max_tilt_deg:
        reasons.append(f"the cube's vertical is {tilt:.1f} deg from the frame's z axis: heights may be off")
    return scale


def _cube_scale(cube_fit, size: float, edge_method: str, camera_centres, reasons: list[str]):
    """Scale and frame of an uncalibrated cloud from the cube found in it. Returns ``(T, scale)``."""
    from plantsplat.traits.cube_fit import cube_frame_transform, decide_up

    decide_up(cube_fit, camera_centres=camera_centres)
    T, sc = cube_frame_transform(cube_fit, size)
    scale = {"source": f"cube_{edge_method}", "scale": sc, "cube_edge_units": cube_fit.edge,
             "cube_edge_method": edge_method, "up_method": cube_fit.up_method}
    if not cube_fit.up_confident:
        reasons.append(f"the vertical direction is uncertain ({cube_fit.up_method}): check the side view")
    return T, scale


def _check_cube_axes(cube_fit, scale: dict, calibrated: bool, reasons: list[str]) -> None:
    measured = [e for e in cube_fit.edge_per_axis if e is not None]
    k = 1.0 if calibrated else scale["scale"]
    scale["cube_edge_cm_per_axis"] = [None if e is None else e * k for e in cube_fit.edge_per_axis]
    if len(measured) > 1 and (max(measured) - min(measured)) / np.mean(measured) > 0.03:
        reasons.append("the cube's edges measured along different axes differ by more than 3 %: the cube is "
                       "distorted in the reconstruction")


def _clusters_below_ground(pts_cm, labels, excl: set) -> list[int]:
    below = []
    for i in range(int(labels.max() + 1)):
        if i in excl:
            continue
        zi = pts_cm[labels == i, 2]
        if len(zi) and np.quantile(zi, 0.9) < -1.0:
            below.append(i)
    return below


def _drop_aruco_box(pts_cm, labels, size: float, notes: list[str], clusters_info: dict):
    """No cube cluster was recognised (a reconstruction too rough for the box test, or the cube fused with
    the plant), but the ArUco calibration puts the cube exactly at the frame's origin, edges along x and y:
    its points are left out before the plant is chosen."""
    h = size / 2 + 0.5
    in_cube = ((np.abs(pts_cm[:, 0]) < h) & (np.abs(pts_cm[:, 1]) < h)
               & (pts_cm[:, 2] > -0.5) & (pts_cm[:, 2] < size + 0.5))
    if not in_cube.any():
        return labels
    labels = labels.copy()
    labels[in_cube] = -1
    notes.append(f"{int(in_cube.sum())} points inside the ArUco cube's known box were left out")
    clusters_info["points_in_aruco_cube_box"] = int(in_cube.sum())
    return labels


def _is_hanging_fruit(q, cols_q, s: TraitsConfig, top: float) -> bool:
    red = fruit_mask(cols_q, s)
    fruit = red.mean() >= s.fruit_join_fraction or (
        s.fruit_join_unripe_cm > 0 and fruit_sized(q, s.fruit_join_unripe_cm)
        and (red | unripe_fruit_mask(cols_q)).mean() >= s.fruit_join_fraction)
    return bool(fruit) and q[:, 2].max() <= top


def _join_fruit(pts_cm, cols, labels, sel, s: TraitsConfig, notes: list[str]) -> list:
    """Fruit-coloured clusters left out as far from the plant but hanging within ``s.fruit_join_cm`` of
    it join the plant (fruit on peduncles too thin to reconstruct). Updates ``sel`` in place."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts_cm[sel.mask])
    top = float(pts_cm[sel.mask, 2].max())
    joined = []
    for e in sel.excluded:
        if e["reason"] != "far from the plant":
            continue
        m = labels == e["label"]
        q = pts_cm[m]
        if not _is_hanging_fruit(q, cols[m], s, top):
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


def _soil_under(P: np.ndarray, soil_z: float | None, disc: tuple | None, notes: list[str]) -> float | None:
    """``soil_z``, lowered to the plant's lowest point over the pot's inside when it is only an upper bound."""
    if soil_z is None or disc is None:
        return soil_z
    inside = np.linalg.norm(P[:, :2] - np.asarray(disc[0]), axis=1) < disc[1]
    if not inside.any() or P[inside, 2].min() >= soil_z:
        return soil_z
    low = float(P[inside, 2].min())
    notes.append(f"the soil was not seen; the plant's lowest point inside the pot ({low:.1f} cm) is taken for it "
                 f"instead of the rim ({soil_z:.1f} cm)")
    return low


def _plant_traits(P, P_centres, C_centres, soil, s: TraitsConfig, notes: list[str]):
    traits: dict = traitdefs.geometric_traits(P, soil_z=soil)
    rob = traitdefs.geometric_traits(P, trim=s.trim, soil_z=soil)
    robust = {k: rob[k] for k in ROBUST_KEYS}
    fruit_centres = None
    if C_centres is not None:
        traits["fruit_count"], fruit_centres = count_fruit(P_centres, C_centres, s)
    else:
        traits["fruit_count"] = None
        notes.append("no colours in the cloud: fruit not counted")
    return traits, robust, fruit_centres


def measure_traits(
    points: np.ndarray,
    colors: np.ndarray | None = None,
    *,
    calibrated: bool,
    opacity: np.ndarray | None = None,
    scales: np.ndarray | None = None,
    camera_centres: np.ndarray | None = None,
    settings: TraitsConfig | None = None,
    cube: CubeSpec | None = None,
    centre_mask: np.ndarray | None = None,
    soil_z: float | None = None,
    soil_disc: tuple | None = None,
) -> TraitResult:
    """Measure plant traits from a point cloud of a plant and the calibration cube.

    The steps: filter the cloud, cluster it (DBSCAN), find and fit the cube, put the cloud in cm with z up
    (the ArUco calibration, cross-checked by the cube, or the cube alone), choose the plant's clusters,
    then measure.

    Args:
        points: ``[N, 3]`` positions (Gaussian centres or any points).
        colors: ``[N, 3]`` uint8 RGB, or None (then no fruit count).
        calibrated: True when ``points`` are already in the ArUco-calibrated frame (cm, z up, ground
            at z = 0); False for an arbitrary frame and scale (the cube then gives both).
        opacity: ``[N]`` Gaussian opacities (0..1) to filter by ``settings.opacity_min``; None keeps all.
        scales: ``[N, 3]`` Gaussian extents (same units as points) for ``settings.max_scale_cm``.
        camera_centres: ``[M, 3]`` camera positions in the same frame (helps find "up" when uncalibrated).
        settings: :class:`TraitsConfig`.
        cube: the cube's geometry (only ``size`` is used); defaults to :class:`CubeSpec` ().
        centre_mask: ``[N]`` bool, True for Gaussian centres when the other points are extent samples
            (:func:`gaussian_extent_points`); fruit are counted on centres only. None: all points.
        soil_z: the soil surface's height in a calibrated cloud (cm): the height is measured from it (else
            the plant's z extent).
        soil_disc: ``(centre xy, radius)`` of the pot's inside when ``soil_z`` is only an upper bound (the
            rim): the soil is then taken no higher than the plant's lowest point over that disc.

    Returns:
        A :class:`TraitResult`; ``quality`` is 'failed' (and every trait None) when the traits cannot
        be measured (empty cloud, no cube in an uncalibrated cloud, no plant).

    Example:
        >>> res = measure_traits(np.zeros((0, 3)), None, calibrated=True)
        >>> res.quality, res.reasons[0][:26]
        ('failed', 'the point cloud is empty (')
    """
    from plantsplat.traits.cluster import far_clusters_reason, select_plant

    s = settings or TraitsConfig()
    size = cube_edge_cm(s, cube)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pts, cols, is_centre, filt = _filter_cloud(points, colors, opacity, scales, centre_mask, s, calibrated)
    if len(pts) < 100:
        return _failed(
            f"the point cloud is empty ({len(pts)} of {filt['input_points']} points left after filtering; need at "
            "least 100): check the export stage and the opacity threshold",
            s,
            clusters={"filter": filt},
        )
    reasons: list[str] = []
    notes: list[str] = []
    if filt["non_finite"]:
        reasons.append(f"{filt['non_finite']} points with non-finite coordinates were dropped")

    labels, eps, first_eps, cube_label, cands = _cluster_and_find_cube(pts, is_centre, centre_mask, s, calibrated,
                                                                       size, notes)
    timings["dbscan"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    cube_fit, edge_method = _fit_cube(None if cube_label is None else pts[labels == cube_label], s, calibrated, size,
                                      opacity is not None or centre_mask is not None, reasons)
    timings["cube"] = time.perf_counter() - t1
    cand_info = [
        {"label": c.label, "points": c.points, "extents": np.round(c.extents, 4).tolist(), "accepted": c.accepted,
         "score": round(c.score, 4), "why_not": c.why}
        for c in cands[:8]
    ]
    clusters_info: dict = {"filter": filt, "eps": eps, "eps_first_pass": first_eps, "min_points": s.min_points,
                           "n_clusters": int(labels.max() + 1), "noise_points": int((labels < 0).sum()),
                           "cube_label": cube_label, "cube_candidates": cand_info}

    if calibrated:
        T, scale, pts_cm = np.eye(4), _aruco_scale(cube_fit, size, edge_method, s, reasons), pts
    elif cube_fit is None:
        return _failed(
            "the cloud is not scaled (no ArUco calibration) and no cube was found in it: cannot give traits in "
            f"cm; make sure the {size:g} cm cube is in the masks and the reconstruction",
            s, scale={"source": None}, clusters=clusters_info,
        )
    else:
        T, scale = _cube_scale(cube_fit, size, edge_method, camera_centres, reasons)
        pts_cm = pts @ T[:3, :3].T + T[:3, 3]
    if cube_fit is not None:
        _check_cube_axes(cube_fit, scale, calibrated, reasons)
    cube_json = None if cube_fit is None else cube_fit.to_dict()

    t2 = time.perf_counter()
    excl = set() if cube_label is None else {cube_label}
    below = _clusters_below_ground(pts_cm, labels, excl)
    excl |= set(below)
    if below:
        notes.append(f"{len(below)} cluster(s) below the ground plane left out")
        clusters_info["below_ground"] = below
    if calibrated and cube_fit is None:
        labels = _drop_aruco_box(pts_cm, labels, size, notes, clusters_info)
    sel = select_plant(pts_cm, labels, exclude=excl, merge_distance=s.merge_distance_cm,
                       min_cluster_fraction=s.min_cluster_fraction, min_cluster_points=s.min_points)
    if sel is None:
        return _failed("no plant cluster found in the cloud (only the cube or noise): check the masks and export",
                       s, scale=scale, cube=cube_json, clusters=clusters_info)
    joined = _join_fruit(pts_cm, cols, labels, sel, s, notes) if cols is not None and s.fruit_join_cm > 0 else []
    plant_mask = sel.mask
    far = far_clusters_reason(sel.excluded, int(plant_mask.sum()))  # what is still left out after fruit joined
    if far:
        sel.reasons.append(far)
    reasons.extend(sel.reasons)
    clusters_info.update({"plant_clusters": sel.clusters, "fruit_joined": joined, "plant_main_fraction": sel.main_fraction,
                          "excluded": sel.excluded[:20], "plant_points": int(plant_mask.sum())})
    P = pts_cm[plant_mask]  # [M, 3]
    C = None if cols is None else cols[plant_mask]
    if len(P) < 50:
        return _failed(f"the plant has only {len(P)} points: the reconstruction is too sparse to measure",
                       s, scale=scale, cube=cube_json, clusters=clusters_info)
    if P[:, 2].min() < -1.0:
        reasons.append(f"plant points reach {P[:, 2].min():.1f} cm below the ground plane: check the vertical")

    soil = _soil_under(P, soil_z, soil_disc, notes) if calibrated else None
    traits, robust, fruit_centres = _plant_traits(P, pts_cm[plant_mask & is_centre],
                                                  None if C is None else cols[plant_mask & is_centre], soil, s, notes)
    timings["plant_and_traits"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    cube_pts = None if cube_label is None else pts_cm[labels == cube_label]
    return TraitResult(
        traits=traits, robust=robust, quality="warning" if reasons else "ok", reasons=reasons, scale=scale,
        cube=cube_json, clusters=clusters_info, settings=asdict(s), plant_points=P, plant_colors=C,
        cube_points=cube_pts, fruit_centres=fruit_centres, transform=T, timings=timings, notes=notes, soil_z=soil,
    )


def gaussian_extent_points(
    means: np.ndarray, scales: np.ndarray, quats: np.ndarray, k_sigma: float
) -> np.ndarray:
    """The centres and the 6 ends of each Gaussian's principal axes at ``k_sigma`` standard deviations.

    ``means [N, 3]``, ``scales [N, 3]`` (activated standard deviations), ``quats [N, 4]`` (w, x, y, z).
    Returns ``[7 N, 3]`` in 7 blocks of N: the centres, then each axis end of every Gaussian (so
    per-Gaussian attributes repeat with ``np.tile(attr, (7, 1))``).

    Example:
        >>> p = gaussian_extent_points(np.zeros((1, 3)), np.array([[1.0, 2, 3]]), np.array([[1.0, 0, 0, 0]]), 2.0)
        >>> float(p[:, 2].max()), float(p[:, 1].min())
        (6.0, -4.0)
    """
    from scipy.spatial.transform import Rotation

    q = np.asarray(quats, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # [N, 3, 3], columns = principal axes
    ax = R * (k_sigma * np.asarray(scales, dtype=np.float64))[:, None, :]  # [N, 3, 3] scaled columns
    means = np.asarray(means, np.float64)
    ends = [means + sgn * ax[:, :, j] for j in range(3) for sgn in (1.0, -1.0)]  # 6 x [N, 3]
    return np.concatenate([means, *ends])  # block k holds point k of every Gaussian


def read_splat_extent_cloud(path: str | Path, opacity_min: float, k_sigma: float) -> dict[str, np.ndarray]:
    """Point cloud of the opaque Gaussians of an Inria-layout ``splat.ply`` with their extents
    (see :func:`gaussian_extent_points`; ``k_sigma`` 0: the centres alone); colours from the SH DC term.
    The PLY's opacity is a logit: it is mapped through the sigmoid before ``opacity_min`` applies."""
    from plantsplat.ply import read_splat

    g = read_splat(path)
    op = 1.0 / (1.0 + np.exp(-np.asarray(g["opacities"], np.float64)))  # [N]
    keep = op >= opacity_min
    means = np.asarray(g["means"], np.float64)[keep]
    scales = np.exp(np.asarray(g["scales"], np.float64)[keep])
    pts = gaussian_extent_points(means, scales, np.asarray(g["quats"])[keep], k_sigma) if k_sigma > 0 else means
    rgb = np.clip(0.5 + 0.28209479177387814 * np.asarray(g["sh0"], np.float64)[keep, 0, :], 0, 1)
    rgb = np.round(rgb * 255).astype(np.uint8)
    centre = np.zeros(len(pts), bool)
    centre[: len(means)] = True
    return {"xyz": pts, "rgb": np.tile(rgb, (len(pts) // max(len(means), 1), 1)), "opacity": None, "scales": None,
            "centre": centre,
            "gaussians": int(keep.sum())}


def cube_edge_cm(s: TraitsConfig, cube: CubeSpec | None) -> float:
    """The cube's edge (cm): ``s.cube_size_cm`` when given, else the recorded ``cube``'s, else the default cube's.

    Example:
        >>> cube_edge_cm(TraitsConfig(), CubeSpec(size=20.0, marker_size=19.2)), cube_edge_cm(TraitsConfig(), None)
        (20.0, 10.0)
    """
    return float(s.cube_size_cm) if s.cube_size_cm is not None else float((cube or CubeSpec()).size)


def traits_csv_text(result_json: dict, plant: str) -> str:
    """One header line and one row: plant, the six traits, robust height/widths, scale, quality."""
    cols = ["plant", *traitdefs.TRAIT_KEYS, *(f"robust_{k}" for k in ROBUST_KEYS), "scale_source",
            "aruco_vs_cube_pct", "quality", "quality_reasons"]
    sc = result_json.get("scale") or {}
    row = [plant, *(result_json.get(k) for k in traitdefs.TRAIT_KEYS),
           *((result_json.get("robust") or {}).get(k) for k in ROBUST_KEYS), sc.get("source"),
           sc.get("aruco_vs_cube_pct"), result_json.get("quality"), " | ".join(result_json.get("quality_reasons", []))]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    w.writerow(["" if x is None else (f"{x:.4f}" if isinstance(x, float) else csv_cell(x)) for x in row])
    return buf.getvalue()


def _camera_centres(ws) -> np.ndarray | None:
    """Camera positions from ``transforms.json`` (camera-to-world matrices), or None."""
    import json

    if not ws.transforms_json.is_file():
        return None
    try:
        tf = json.loads(ws.transforms_json.read_text())
        mats = [np.asarray(f["transform_matrix"], dtype=np.float64) for f in tf.get("frames", [])]
        c = np.array([m[:3, 3] for m in mats if m.shape == (4, 4)])
        return c if len(c) >= 3 else None
    except (ValueError, KeyError, TypeError):
        log.warning("%s: could not read camera positions; the vertical is taken from the cube alone", ws.transforms_json)
        return None


def traits_workspace(ws, cfg=None, *, points_path: str | Path | None = None, calibrated: bool | None = None,
                     figure: bool = True) -> dict:
    """Run the traits stage on a workspace; returns the ``traits.json`` content.

    Reads ``WS/export/points.ply`` (or ``points_path``) and ``WS/poses.json`` (``scale_source``
    'aruco' means calibrated), writes ``traits.json``, ``traits.csv`` and ``traits.png``. The height is
    measured from the soil (:func:`plantsplat.traits.checks.soil_level`). ``quality`` is ``failed`` when
    nothing could be measured or a check of a stage or of the measurement fails (the files are written
    all the same; the commands then exit with :data:`plantsplat.errors.EXIT_RESULT_FAILED`).

    Usage:
        from plantsplat.workspace import Workspace
        out = traits_workspace(Workspace("ws/plant_01"))
        out["height_cm"], out["quality"]
    """
    from plantsplat.io import read_json, write_json_atomic, write_text_atomic
    from plantsplat.markers import recorded_cube
    from plantsplat.ply import is_splat, read_point_cloud
    from plantsplat.workspace import Workspace

    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    s = cfg if isinstance(cfg, TraitsConfig) else TraitsConfig()
    if points_path:
        ply = Path(points_path)
        if not ply.is_file():
            raise PlantsplatError(f"{ply}: point cloud not found; give an exported points.ply or splat.ply")
        extents = is_splat(ply)  # a splat PLY is read as Gaussians (its opacity is a logit), at any sigma
    elif s.extent_sigma > 0 and (ws.splat_ply.is_file() or not ws.points_ply.is_file()):
        ply, extents = ws.splat_ply, True
        ws.require(ply, "export")
    else:
        ply, extents = ws.points_ply, False
        ws.require(ply, "export")
        if s.extent_sigma > 0:
            log.warning("traits: %s is missing, so the Gaussians' extents are not sampled (centres only, which "
                        "underestimates the traits); re-run `plantsplat export %s`", ws.splat_ply, ws.root)
    if calibrated is None:
        if ws.poses_json.is_file():
            src = read_json(ws.poses_json).get("scale_source", "none")
            calibrated = src == "aruco"
        else:
            raise PlantsplatError(
                f"{ws.poses_json}: missing, so the cloud's scale is unknown; run `plantsplat poses {ws.root}` "
                "or pass --calibrated / --no-calibrated"
            )
    if extents:
        data = read_splat_extent_cloud(ply, s.opacity_min, s.extent_sigma)
        log.info("traits: %s (%d Gaussians%s)", ply, data["gaussians"],
                 f" with their extents at {s.extent_sigma:.2g} sigma" if s.extent_sigma > 0 else ", centres only")
    else:
        data = read_point_cloud(ply, "run `plantsplat export` first or pass --points")
    log.info("traits: %s (%d points, %s)", ply, len(data["xyz"]), "calibrated cm" if calibrated else "unscaled")
    cams = _camera_centres(ws)
    soil_z, soil_source, soil_disc = soil_level(ws, calibrated)
    cube = recorded_cube(ws.markers_json)  # the cube the poses stage measured with
    res = measure_traits(data["xyz"], data["rgb"], calibrated=calibrated, opacity=data["opacity"],
                         scales=data["scales"], camera_centres=None if calibrated else cams, settings=s,
                         centre_mask=data.get("centre"), soil_z=soil_z, soil_disc=soil_disc, cube=cube)
    out = res.to_json()
    out["input"] = str(ply)
    out["soil_source"] = soil_source
    out["scale"]["calibrated_input"] = bool(calibrated)
    se = None
    if calibrated and ws.poses_json.is_file():
        se = (read_json(ws.poses_json).get("scale_uncertainty") or {}).get("relative_se")
        out["scale"]["standard_error_pct"] = None if se is None else round(100.0 * se, 3)  # the cube's, from poses
    soil = _height_bounds(out, res, soil_z if calibrated else None, soil_disc, se)
    _judge(out, res, ws, cams if calibrated else None, soil, cube_edge_cm(s, cube))
    write_json_atomic(ws.traits_json, out)
    write_text_atomic(ws.traits_csv, traits_csv_text(out, ws.root.name))
    if figure and res.plant_points is not None:
        from plantsplat.traits.figures import traits_figure

        traits_figure(res, ws.traits_png, title=ws.root.name)
    if out["quality"] == "failed":
        log.error("traits: FAILED: %s (details in %s)", "; ".join(out["quality_reasons"][:3]), ws.traits_json)
    for r in out["quality_reasons"] if out["quality"] != "failed" else ():
        log.warning("traits: %s", r)
    for r in res.notes:
        log.info("traits: %s", r)
    return out


def _height_bounds(out: dict, res: TraitResult, soil_z: float | None, disc: tuple | None, scale_se: float | None):
    """The soil's interval and the height's bounds (:mod:`plantsplat.traits.height`) into ``out``
    (``soil_interval_cm``, ``height_bounds_cm``); returns the soil interval (None: no pot, or no plant)."""
    from plantsplat.segment.object3d import POT_SLAB_CM
    from plantsplat.traits.height import height_bounds, soil_interval

    P = res.plant_points
    if P is None or not len(P) or out.get("height_cm") is None:
        return None
    soil = None
    if soil_z is not None:
        lowest = None
        if disc is not None:
            inside = np.linalg.norm(P[:, :2] - np.asarray(disc[0]), axis=1) < disc[1]
            lowest = float(P[inside, 2].min()) if inside.any() else None
        soil = soil_interval(soil_z, disc is None, POT_SLAB_CM, lowest)
        out["soil_interval_cm"] = [round(soil.low, 3), round(soil.high, 3)]
    lo, hi = height_bounds(float(P[:, 2].max()), soil, scale_se, out.get("height_extent_cm"))
    out["height_bounds_cm"] = [round(lo, 3), round(hi, 3)]
    return soil


def _judge(out: dict, res: TraitResult, ws, cams: np.ndarray | None, soil, cube_cm: float) -> None:
    """Every stage's checks and the measurement's own (:mod:`plantsplat.traits.checks`) into ``out``'s ``checks``,
    ``quality`` and ``quality_reasons``."""
    from plantsplat.checks import quality
    from plantsplat.traits.checks import result_checks, stage_checks

    checks = stage_checks(ws)
    if res.plant_points is not None:
        top = float(res.plant_points[:, 2].max())
        checks += result_checks(res.traits, len(res.plant_points), top if cams is not None else None,
                                None if cams is None else float(cams[:, 2].max()), cube_cm,
                                height_bounds=out.get("height_bounds_cm"), soil_how="" if soil is None else soil.how)
    out["checks"] = [c.as_dict() for c in checks]
    verdict = quality(checks)
    order = ["ok", "warning", "failed"]
    out["quality"] = max(res.quality, verdict, key=order.index)
    out["quality_reasons"] = [f"check {c.line()}" for c in checks if not c.passed] + list(res.reasons)

"""Plant traits from a point cloud: cluster, find and measure the cube, select the plant, measure.

The library entry point is :func:`measure_traits` (any point cloud, calibrated or not); the stage's,
over a workspace, is :func:`plantsplat.traits.stage.run`.

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

Fruit are counted and joined by :mod:`plantsplat.traits.fruit`.

Example:
    >>> import numpy as np
    >>> from plantsplat.cube import cube_surface_points
    >>> rng = np.random.default_rng(0)
    >>> cube = cube_surface_points(10.0, 6000, rng, faces=("+x", "-x", "+y", "-y", "top"))
    >>> plant = rng.uniform([-8, -6, 5], [8, 6, 20], (20000, 3)) + [25, 0, 0]
    >>> res = measure_traits(np.concatenate([cube, plant]), None, calibrated=True)
    >>> res.quality, round(res.traits["height_cm"], 1)
    ('ok', 15.0)
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict

import numpy as np
from scipy.spatial import cKDTree

from plantsplat import traitdefs
from plantsplat.cube import CubeSpec, in_cube_box
from plantsplat.log import get_logger
from plantsplat.traits.cluster import dbscan, far_clusters_reason, select_plant
from plantsplat.traits.config import ROBUST_KEYS, MeasureConfig, TraitsConfig, cube_edge_cm
from plantsplat.traits.cube_fit import cube_frame_transform, decide_up, find_cube_cluster, fit_cube_planes, use_envelope
from plantsplat.traits.fruit import count_fruit, join_fruit
from plantsplat.traits.result import TraitResult, failed_result

log = get_logger(__name__)

SETTINGS = MeasureConfig()
"""The tuning of the plant's selection (every value documented in :class:`MeasureConfig`)."""
LISTED_CANDIDATES = 8
"""``traits.json`` lists this many of the cube's candidate clusters, the likeliest first."""
LISTED_EXCLUDED = 20
"""``traits.json`` lists this many of the clusters left out of the plant."""


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
    return pts, cols, is_centre, _gaussian_of(centre_mask, n_in)[keep], filt


def _gaussian_of(centre_mask, n: int) -> np.ndarray:
    """``[n]`` the Gaussian each point belongs to: the extent samples of :func:`plantsplat.ply.gaussian_extent_points`
    come in blocks of the Gaussians' count, the centres first; any other cloud, each point its own."""
    m = None if centre_mask is None else np.asarray(centre_mask, bool)
    k = 0 if m is None else int(m.sum())
    if k and n % k == 0 and m[:k].all():
        return np.arange(n) % k
    return np.arange(n)


def _sample_centres(pts: np.ndarray, is_centre: np.ndarray, gaussian: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """For each point of ``mask``, the centre of the Gaussian it was sampled from (itself where that centre was
    filtered out). ``[M, 3]``"""
    centre = np.full((int(gaussian.max(initial=-1)) + 1, 3), np.nan)
    centre[gaussian[is_centre]] = pts[is_centre]
    out = centre[gaussian[mask]]
    missing = np.isnan(out[:, 0])
    out[missing] = pts[mask][missing]
    return out


def _cluster_and_find_cube(pts, is_centre, centre_mask, s: TraitsConfig, calibrated: bool, size: float,
                           notes: list[str]):
    """DBSCAN clusters and the cube's cluster among them (clustered again tighter when the cube touches
    another cluster). Returns ``(labels, eps, first_eps, cube_label, candidates)``."""
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
    decide_up(cube_fit, camera_centres=camera_centres)
    T, sc = cube_frame_transform(cube_fit, size)
    scale = {"source": f"cube_{edge_method}", "scale": sc, "cube_edge_units": cube_fit.edge,
             "cube_edge_method": edge_method, "up_method": cube_fit.up_method}
    if not cube_fit.up_confident:
        reasons.append(f"the vertical direction is uncertain ({cube_fit.up_method}): check the side view")
    return T, scale


def _check_cube_axes(cube_fit, scale: dict, calibrated: bool, reasons: list[str]) -> None:
    k = 1.0 if calibrated else scale["scale"]
    scale["cube_edge_cm_per_axis"] = [None if e is None else e * k for e in cube_fit.edge_per_axis]
    spread = cube_fit.axis_spread()
    scale["cube_axis_spread"] = spread
    if spread is not None and spread > SETTINGS.cube_axes_tolerance:
        reasons.append(f"the cube's edges between opposite faces differ by {100 * spread:.1f} % from one axis to "
                       f"another (more than {100 * SETTINGS.cube_axes_tolerance:.0f} %): the cube is distorted in "
                       "the reconstruction")


def _clusters_below_ground(pts_cm, labels, excl: set) -> list[int]:
    """Clusters under the ground plane (z = 0): wholly below it, or nine tenths of them more than a cm below (the
    Gaussians' ends reach a little under what they draw). Nothing of the plant grows under the ground."""
    below = []
    for i in range(int(labels.max() + 1)):
        if i in excl:
            continue
        zi = pts_cm[labels == i, 2]
        if len(zi) and (zi.max() < 0.0 or np.quantile(zi, SETTINGS.below_ground_quantile) < -1.0):
            below.append(i)
    return below


def _drop_aruco_box(pts_cm, labels, gaussian: np.ndarray, cube_label: int | None, size: float, notes: list[str],
                    clusters_info: dict):
    """The ArUco calibration puts the cube exactly at the frame's origin, edges along x and y, and nothing of the plant
    is inside it: the points in its box (grown by half a cm) are left out, with every extent sample of a Gaussian
    whose centre is there (``gaussian [N]``: each point's Gaussian), before the plant is chosen. It catches what the
    cube's cluster missed: a reconstruction too rough for the box test, the cube fused with the plant, pieces of its
    faces in clusters of their own, and its Gaussians' ends reaching out of the box."""
    in_cube = in_cube_box(pts_cm, size, 0.5)
    in_cube |= np.isin(gaussian, gaussian[in_cube])
    in_cube &= (labels >= 0) & (labels != (-1 if cube_label is None else cube_label))  # the cube's cluster: out
    if not in_cube.any():
        return labels
    labels = labels.copy()
    labels[in_cube] = -1
    notes.append(f"{int(in_cube.sum())} points of Gaussians inside the ArUco cube's known box were left out")
    clusters_info["points_in_aruco_cube_box"] = int(in_cube.sum())
    return labels


def _cube_fragments(pts_cm, labels, excl: set, size: float) -> list[int]:
    """Small clusters that belong to the cube rather than to the plant: on the cube's box (their median point within
    ``SETTINGS.fragment_reach`` of the cube's edge of it), nearer it than the plant's body (the largest cluster
    left) and under a twentieth of the body's size. Pieces of the cube's faces whose Gaussians sit just outside its
    box make such clusters; a leaf apart from its petiole, or fruit hanging over the pot's rim on the cube's side,
    lie farther out (8-9 cm from the box on two synthetic captures, 2026-11-27), however far their body is."""
    ids = [i for i in range(int(labels.max() + 1)) if i not in excl and (labels == i).any()]
    if len(ids) < 2:
        return []
    sizes = {i: int((labels == i).sum()) for i in ids}
    body = max(ids, key=sizes.get)
    rng = np.random.default_rng(0)
    b = pts_cm[labels == body]
    tree = cKDTree(b[rng.choice(len(b), min(len(b), SETTINGS.body_sample), replace=False)])
    h = size / 2
    out = []
    for i in ids:
        if i == body or sizes[i] * SETTINGS.fragment_ratio > sizes[body]:
            continue
        q = pts_cm[labels == i]
        to_box = np.linalg.norm(np.maximum(np.abs(q[:, :2]) - h, 0.0), axis=1) + np.maximum(q[:, 2] - size, 0.0)
        gap = np.median(to_box)
        if gap < SETTINGS.fragment_reach * size and gap < np.median(tree.query(q, k=1)[0]):
            out.append(i)
    return out


def _soil_under(P: np.ndarray, soil_z: float | None, disc: tuple | None, notes: list[str]
                ) -> tuple[float | None, float | None]:
    """``soil_z``, lowered to the plant's lowest point over the pot's inside when it is only an upper bound, and how
    that lowest centimetre of the plant spreads over the inside (its RMS distance from the pot's axis over the
    inside's radius: a crown and petioles' feet stand near the axis; soil or pot wall taken for plant spreads
    like the soil, 0.71 for a layer even over the inside). ``P``: the plant's Gaussian centres, which lie on the
    surfaces they draw: the ends of their extents reach below them (on foreign render 101, those of Gaussians
    drawing the soil reached 1.2 cm under it, the centres 0.35 cm)."""
    if soil_z is None or disc is None:
        return soil_z, None
    r = np.linalg.norm(P[:, :2] - np.asarray(disc[0]), axis=1)
    inside = r < disc[1]
    if not inside.any() or P[inside, 2].min() >= soil_z:
        return soil_z, None
    low = float(P[inside, 2].min())
    base = inside & (P[:, 2] < low + 1.0)
    spread = float(np.sqrt(np.mean(r[base] ** 2)) / disc[1])
    notes.append(f"the soil was not seen; the plant's lowest point inside the pot ({low:.1f} cm) is taken for it "
                 f"instead of the rim ({soil_z:.1f} cm)")
    return low, spread


def _plant_traits(P, P_centres, C_centres, soil, s: TraitsConfig, notes: list[str], same_fruit=None):
    traits: dict = traitdefs.geometric_traits(P, soil_z=soil)
    rob = traitdefs.geometric_traits(P, trim=s.trim, soil_z=soil)
    robust = {k: rob[k] for k in ROBUST_KEYS}
    fruit_centres = None
    if C_centres is not None:
        traits["fruit_count"], fruit_centres = count_fruit(P_centres, C_centres, s, same_fruit=same_fruit)
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
    fruit_judge: Callable[[list[np.ndarray], np.ndarray], list[int]] | None = None,
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
            (:func:`plantsplat.ply.gaussian_extent_points`); fruit are counted on centres only. None: all points.
        soil_z: the soil surface's height in a calibrated cloud (cm): the height is measured from it (else
            the plant's z extent).
        soil_disc: ``(centre xy, radius)`` of the pot's inside when ``soil_z`` is only an upper bound (the
            rim): the soil is then taken no higher than the plant's lowest point over that disc.
        fruit_judge: ``(pieces [N_i, 3] in cm, T [4, 4] from the cloud's frame to cm) -> group of each piece``: which
            pieces of fruit-coloured points are one fruit (:func:`plantsplat.traits.fruit_views.judge_by_views`);
            None: every piece is a fruit.

    Returns:
        A :class:`TraitResult`; ``quality`` is 'failed' (and every trait None) when the traits cannot
        be measured (empty cloud, no cube in an uncalibrated cloud, no plant).

    Example:
        >>> res = measure_traits(np.zeros((0, 3)), None, calibrated=True)
        >>> res.quality, res.reasons[0][:26]
        ('failed', 'the point cloud is empty (')
    """
    s = settings or TraitsConfig()
    size = cube_edge_cm(s, cube)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pts, cols, is_centre, gaussian, filt = _filter_cloud(points, colors, opacity, scales, centre_mask, s, calibrated)
    if len(pts) < 100:
        return failed_result(
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
        for c in cands[:LISTED_CANDIDATES]
    ]
    clusters_info: dict = {"filter": filt, "eps": eps, "eps_first_pass": first_eps, "min_points": s.min_points,
                           "n_clusters": int(labels.max() + 1), "noise_points": int((labels < 0).sum()),
                           "cube_label": cube_label, "cube_candidates": cand_info}

    if calibrated:
        T, scale, pts_cm = np.eye(4), _aruco_scale(cube_fit, size, edge_method, s, reasons), pts
    elif cube_fit is None:
        return failed_result(
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
    if calibrated:  # first: a piece of the cube may hold a cluster up above the ground
        labels = _drop_aruco_box(pts_cm, labels, gaussian, cube_label, size, notes, clusters_info)
    below = _clusters_below_ground(pts_cm, labels, excl)
    excl |= set(below)
    if below:
        notes.append(f"{len(below)} cluster(s) below the ground plane left out")
        clusters_info["below_ground"] = below
    if calibrated:
        pieces = _cube_fragments(pts_cm, labels, excl, size)
        excl |= set(pieces)
        if pieces:
            notes.append(f"{len(pieces)} small cluster(s) nearer the cube than the plant left out")
            clusters_info["cube_fragments"] = pieces
    sel = select_plant(pts_cm, labels, exclude=excl, merge_distance=s.merge_distance_cm,
                       min_cluster_fraction=s.min_cluster_fraction, min_cluster_points=s.min_points)
    if sel is None:
        return failed_result("no plant cluster found in the cloud (only the cube or noise): check the masks and export",
                       s, scale=scale, cube=cube_json, clusters=clusters_info)
    joined = join_fruit(pts_cm, cols, labels, sel, s, notes) if cols is not None and s.fruit_join_cm > 0 else []
    plant_mask = sel.mask
    far = far_clusters_reason(sel.excluded, int(plant_mask.sum()))  # what is still left out after fruit joined
    if far:
        sel.reasons.append(far)
    reasons.extend(sel.reasons)
    clusters_info.update({"plant_clusters": sel.clusters, "fruit_joined": joined, "plant_main_fraction": sel.main_fraction,
                          "excluded": sel.excluded[:LISTED_EXCLUDED], "plant_points": int(plant_mask.sum())})
    P = pts_cm[plant_mask]  # [M, 3]
    C = None if cols is None else cols[plant_mask]
    centres = _sample_centres(pts_cm, is_centre, gaussian, plant_mask) if centre_mask is not None else None
    if len(P) < SETTINGS.min_plant_points:
        return failed_result(f"the plant has only {len(P)} points: the reconstruction is too sparse to measure",
                       s, scale=scale, cube=cube_json, clusters=clusters_info)
    if P[:, 2].min() < -1.0:
        reasons.append(f"plant points reach {P[:, 2].min():.1f} cm below the ground plane: check the vertical")

    soil, spread = _soil_under(pts_cm[plant_mask & is_centre], soil_z, soil_disc, notes) if calibrated else (None, None)
    same_fruit = None if fruit_judge is None else (lambda pieces: fruit_judge(pieces, T))
    traits, robust, fruit_centres = _plant_traits(P, pts_cm[plant_mask & is_centre],
                                                  None if C is None else cols[plant_mask & is_centre], soil, s, notes,
                                                  same_fruit)
    timings["plant_and_traits"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    cube_pts = None if cube_label is None else pts_cm[labels == cube_label]
    return TraitResult(
        traits=traits, robust=robust, quality="warning" if reasons else "ok", reasons=reasons, scale=scale,
        cube=cube_json, clusters=clusters_info, settings=asdict(s), plant_points=P, plant_colors=C,
        plant_centres=centres,
        plant_gaussians=np.unique(gaussian[plant_mask & is_centre]) if centre_mask is not None else None,
        cube_points=cube_pts, fruit_centres=fruit_centres, transform=T, timings=timings, notes=notes, soil_z=soil,
        base_spread=spread,
    )

"""Find the calibration cube among the clusters and measure it by fitting its faces' planes.

Following the paper (section 2.4): each DBSCAN cluster's oriented bounding box (Open3D's minimal
OBB) is tested for a cube's shape: three near-equal robust extents, points lying on the box's
surface (a reconstructed cube is a hollow shell) and at least three faces well covered. The best
candidate is then measured by fitting its faces' planes with RANSAC (Open3D ``segment_plane``, each
plane refined by least squares on the points assigned to it), grouping the planes into three
orthogonal directions and averaging the distances between parallel (opposite) faces: that is the
cube edge ``l_hat``; the metric scale is ``s = 10 cm / l_hat``.

The cube also gives the ground plane and "up": it stands on the ground, so one of its three axes is
vertical and its bottom face lies on the ground. Which axis and sign is decided by, in order:
the camera centres when known (all cameras are above the ground; a vertical plane through the cube
has cameras on both sides), else the unseen bottom face (a face resting on the ground is not
reconstructed, so it has far fewer points than its opposite face). Without either cue the choice is
flagged as ambiguous.

Example:
    >>> import numpy as np
    >>> from plantsplat.cube import cube_surface_points
    >>> from plantsplat.traits.cube_fit import fit_cube_planes
    >>> rng = np.random.default_rng(0)
    >>> pts = cube_surface_points(10.0, 6000, rng, faces=("+x", "-x", "+y", "-y", "top"))
    >>> fit = fit_cube_planes(pts, size_hint=10.0)
    >>> round(fit.edge, 3)
    10.0
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from plantsplat.cube import FACE_NAMES
from plantsplat.log import get_logger
from plantsplat.traits.config import CubeFitConfig

log = get_logger(__name__)

SETTINGS = CubeFitConfig()
"""The tuning of the cube's recognition and fit (every value documented in :class:`CubeFitConfig`)."""


@dataclass
class CubeCandidate:
    label: int
    points: int
    extents: list[float]
    """Robust extents (1 %-99 % quantiles) along the OBB axes, sorted decreasing."""
    equality: float
    """Smallest over largest extent (1 for a cube)."""
    surface_fraction: float
    """Fraction of points within 8 % of the extent from the box surface."""
    faces_covered: int
    """Faces whose 4x4 grid of cells is at least 60 % occupied."""
    score: float
    accepted: bool
    why: str = ""


@dataclass
class CubeFit:
    """The cube measured by plane fitting (all lengths in the input cloud's units)."""

    edge: float
    """Mean distance between opposite faces (the measured edge length ``l_hat``)."""
    edge_per_axis: list[float | None]
    """Distance between the two faces of each axis (None where only one face was found)."""
    axes: np.ndarray
    """[3, 3] orthonormal cube axes (rows), from the fitted face normals."""
    centre: np.ndarray
    """[3] cube centre."""
    faces: list[dict]
    """Fitted planes: axis, normal [3], offset d (n.x + d = 0), inliers, rms residual."""
    plane_rms: float
    """RMS point-to-plane residual over all assigned points."""
    up: np.ndarray | None = None
    """[3] unit vector, "up" (normal of the top face)."""
    up_axis: int | None = None
    up_method: str = ""
    up_confident: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def bottom_centre(self) -> np.ndarray:
        """Centre of the bottom face (the origin of the calibrated frame). Needs ``up``."""
        assert self.up is not None
        return self.centre - self.up * self.edge / 2

    def axis_spread(self) -> float | None:
        """How much the edges of the axes whose two opposite faces were both fitted differ: (largest - smallest) /
        mean, None with fewer than two such axes. An axis with one face seen (the bottom, on the ground) is left
        out: its extent is bounded by the ground on one side and by the Gaussians' reach on the other, not
        measured as the others are (it came out 2-4 % shorter on most captures of 2026-11-27)."""
        both = self.extra.get("edge_per_axis_planes", self.edge_per_axis)
        edges = [e for e, b in zip(self.edge_per_axis, both) if e is not None and b is not None]
        if len(edges) < 2:
            return None
        return float((max(edges) - min(edges)) / np.mean(edges))

    def to_dict(self) -> dict:
        return {
            "edge": self.edge,
            "edge_per_axis": self.edge_per_axis,
            "axes": self.axes.tolist(),
            "centre": self.centre.tolist(),
            "up": None if self.up is None else self.up.tolist(),
            "up_method": self.up_method,
            "up_confident": self.up_confident,
            "edge_method": self.extra.get("edge_method", "planes"),
            **{k: self.extra[k] for k in ("edge_planes", "edge_per_axis_planes", "envelope_quantile")
               if k in self.extra},
            "faces_fitted": len(self.faces),
            "plane_rms": self.plane_rms,
            "faces": [
                {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in f.items()} for f in self.faces
            ],
        }


def _robust_obb(points: np.ndarray, max_hull_points: int = 5000):
    """Minimal OBB axes ``[3, 3]`` (rows) and the 1 %..99 % extents of the points along them."""
    sub = points
    if len(points) > max_hull_points:  # the box orientation from a subset; extents from all points
        sub = points[np.random.default_rng(0).choice(len(points), max_hull_points, replace=False)]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sub))
    R = None
    for robust in (False, True):
        try:
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                obb = pc.get_minimal_oriented_bounding_box(robust=robust)
        except RuntimeError:
            continue
        Rc = np.asarray(obb.R).T  # rows = axes
        if np.all(np.asarray(obb.extent) > 0) and np.allclose(Rc @ Rc.T, np.eye(3), atol=1e-6):
            R = Rc
            break
    if R is None:
        # degenerate (flat/collinear) clusters: fall back to PCA axes
        c = points - points.mean(0)
        R = np.linalg.svd(c, full_matrices=False)[2]
    proj = (points - points.mean(0)) @ R.T  # [N, 3]
    q = SETTINGS.extent_quantile
    lo, hi = np.quantile(proj, [q, 1.0 - q], axis=0)
    return R, lo, hi, proj


def evaluate_cube_candidate(
    points: np.ndarray, label: int, cube_size: float | None, min_points: int = 200
) -> CubeCandidate:
    """Score one cluster as the cube. ``cube_size`` (cloud units) when known, else None."""
    n = len(points)
    if n < min_points:
        return CubeCandidate(label, n, [], 0.0, 0.0, 0, 0.0, False, "too few points")
    # quick rejection by the PCA extents (any axes of a cube give extents within a factor sqrt(3))
    c, k = points - points.mean(0), SETTINGS
    axes = np.linalg.svd(c[:: max(1, n // k.pca_sample)], full_matrices=False)[2]
    lo, hi = np.quantile(c @ axes.T, [k.extent_quantile, 1.0 - k.extent_quantile], axis=0)
    pe = hi - lo
    small, large = k.pca_size_range
    if pe.min() < pe.max() / k.pca_max_ratio or (cube_size is not None
                                                 and not small * cube_size < pe.max() < large * cube_size):
        return CubeCandidate(label, n, sorted(pe.tolist(), reverse=True), float(pe.min() / pe.max()), 0.0, 0, 0.0,
                             False, "PCA extents are not a cube's")
    # box orientations to try: the minimal OBB of all points, of the core (without the 5 % farthest
    # points, e.g. attached floaters), and the cube frame from fitted face planes (noise-robust)
    best = None
    from_median = np.linalg.norm(points - np.median(points, 0), axis=1)
    core = points[from_median <= np.quantile(from_median, k.core_share)]
    for attempt in range(3):
        if attempt == 0:
            R = _robust_obb(points)[0]
        elif attempt == 1:
            R = _robust_obb(core)[0]
        else:
            sub = points[:: max(1, n // k.orientation_sample)]  # the orientation only: a subset is enough
            fit = fit_cube_planes(sub, size_hint=cube_size, max_planes=k.orientation_planes)
            if fit is None:
                break
            R = fit.axes
        cand = _box_candidate(points, R, label, cube_size)
        if best is None or (cand.accepted, cand.score) > (best.accepted, best.score):
            best = cand
        if best.accepted and best.score > 0.5:
            break
    return best


def _box_candidate(points: np.ndarray, R: np.ndarray, label: int, cube_size: float | None) -> CubeCandidate:
    """Cube-likeness of ``points`` in the box frame with axes ``R [3, 3]`` (rows)."""
    n, k = len(points), SETTINGS
    proj = (points - points.mean(0)) @ R.T  # [N, 3]
    lo, hi = np.quantile(proj, [k.extent_quantile, 1.0 - k.extent_quantile], axis=0)
    ext = hi - lo
    order = np.argsort(-ext)
    ext_sorted = ext[order]
    equality = float(ext_sorted[-1] / max(ext_sorted[0], 1e-12))
    size = float(np.mean(ext))
    tol = k.surface_band * size
    dist_to_surface = np.min(np.concatenate([np.abs(proj - lo), np.abs(hi - proj)], axis=1), axis=1)
    surface = float(np.mean(dist_to_surface < tol))
    covered = 0
    for ax in range(3):
        others = [a for a in range(3) if a != ax]
        for side in (lo[ax], hi[ax]):
            on = np.abs(proj[:, ax] - side) < tol
            if on.sum() < k.face_min_points:
                continue
            uv = (proj[on][:, others] - lo[others]) / np.maximum(ext[others], 1e-12)
            cells = np.clip((uv * k.face_grid).astype(int), 0, k.face_grid - 1)
            occ = len(np.unique(cells[:, 0] * k.face_grid + cells[:, 1])) / k.face_grid**2
            covered += occ >= k.face_cover
    why = []
    if equality < k.min_equality:
        why.append(f"extents {np.round(ext_sorted, 3).tolist()} not equal")
    if surface < k.min_surface:
        why.append(f"only {surface:.0%} of points on the box surface")
    if covered < 3:
        why.append(f"only {covered} faces covered")
    if cube_size is not None and not (k.size_range[0] * cube_size <= size <= k.size_range[1] * cube_size):
        why.append(f"size {size:.3g} is not the cube's {cube_size:.3g}")
    score = equality * surface * covered / len(FACE_NAMES)
    return CubeCandidate(
        label, n, ext_sorted.tolist(), equality, surface, int(covered), float(score), not why, "; ".join(why)
    )


def find_cube_cluster(
    points: np.ndarray, labels: np.ndarray, cube_size: float | None, max_clusters: int = 30
) -> tuple[int | None, list[CubeCandidate]]:
    """The label of the cluster that is the cube (None if none qualifies) and every candidate tried."""
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    ids = ids[np.argsort(-counts)][:max_clusters]
    cands = [evaluate_cube_candidate(points[labels == i], int(i), cube_size) for i in ids]
    ok = [c for c in cands if c.accepted]
    if not ok:
        return None, cands
    best = max(ok, key=lambda c: c.score)
    return best.label, cands


def _lsq_plane(pts: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane through ``pts [M, 3]``: ``(normal [3], d, rms)`` with ``n.x + d = 0``."""
    c = pts.mean(0)
    _, s, vt = np.linalg.svd(pts - c, full_matrices=False)
    nrm = vt[2]
    rms = float(s[2] / np.sqrt(len(pts)))
    return nrm, float(-nrm @ c), rms


def _ransac_planes(pts: np.ndarray, thr: float, max_planes: int, iterations: int, seed: int):
    """Planes found one after another by RANSAC (Open3D), each refitted by least squares."""
    o3d.utility.random.seed(seed)
    remaining = np.arange(len(pts))
    planes: list[tuple[np.ndarray, float]] = []
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        least = max(SETTINGS.plane_min_points, SETTINGS.plane_min_share * len(pts))
        for _ in range(max_planes):
            if len(remaining) < least:
                break
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[remaining]))
            _, inl = pc.segment_plane(thr, 3, iterations)
            inl = np.asarray(inl, dtype=np.int64)
            if len(inl) < least:
                break
            nrm, d, _ = _lsq_plane(pts[remaining[inl]])
            planes.append((nrm, d))
            remaining = np.delete(remaining, inl)
    return planes


def _nearest_plane(pts: np.ndarray, planes, thr: float):
    """Distances ``[N, P]`` to each plane, the nearest plane per point, and whether it is within the inlier band."""
    dist = np.stack([np.abs(pts @ n + d) for n, d in planes], axis=1)
    return dist, dist.argmin(1), dist.min(1) < SETTINGS.inlier_band * thr


def _refine_planes(pts: np.ndarray, planes, thr: float):
    """Every point goes to its nearest plane (within the inlier band); each plane is refitted to its points, twice."""
    for _ in range(2):
        _, near, ok = _nearest_plane(pts, planes, thr)
        new = []
        for k, (n0, d0) in enumerate(planes):
            sel = pts[ok & (near == k)]
            if len(sel) < SETTINGS.refit_min_points:
                new.append((n0, d0))
                continue
            n, d, _ = _lsq_plane(sel)
            if n @ n0 < 0:
                n, d = -n, -d
            new.append((n, d))
        planes = new
    return planes


def _group_directions(planes, counts: np.ndarray) -> list[list[int]]:
    """Planes grouped into (up to) three orthogonal directions, most-supported planes first."""
    cos_par, sin_par = np.cos(np.radians(SETTINGS.parallel_deg)), np.sin(np.radians(SETTINGS.parallel_deg))
    groups: list[list[int]] = []
    for k in np.argsort(-counts):
        n = planes[k][0]
        for g in groups:
            if abs(n @ planes[g[0]][0]) > cos_par:
                g.append(int(k))
                break
        else:
            if all(abs(n @ planes[g[0]][0]) < sin_par for g in groups) and len(groups) < 3:
                groups.append([int(k)])
    return groups


def _two_sides(planes, group: list[int], counts: np.ndarray, size: float) -> list[list]:
    """Within a direction, duplicate fits of the same face (offsets closer than a share of the edge) merged;
    the two best-supported sides, each a list of ``(plane index, position along the direction)``."""
    ref = planes[group[0]][0]
    members = []
    for k in group:
        n, d = planes[k]
        members.append((k, -d if n @ ref > 0 else d))  # position along ref
    members.sort(key=lambda m: -m[1])
    sides: list[list] = []
    for m in members:
        if sides and abs(m[1] - sides[-1][0][1]) < SETTINGS.duplicate_share * size:
            sides[-1].append(m)
        else:
            sides.append([m])
    return sorted(sides, key=lambda sd: -sum(counts[k] for k, _ in sd))[:2]


def _side_planes(pts, planes, groups, counts, near, ok, size: float):
    """One plane per side of each direction, fitted to the points of its merged planes."""
    side_axis: list[int] = []
    side_planes: list[tuple[np.ndarray, float]] = []
    for gi, g in enumerate(groups):
        for sd in _two_sides(planes, g, counts, size):
            idx = np.isin(near, [k for k, _ in sd]) & ok
            if idx.sum() < SETTINGS.refit_min_points:
                continue
            n, d, _ = _lsq_plane(pts[idx])
            side_axis.append(gi)
            side_planes.append((n, d))
    return side_axis, side_planes


def _final_face_fits(pts, side_planes, thr: float):
    """Final fits: every point goes to its nearest face; points near a cube edge (close to two faces) are
    left out, so that one face's points never pull on another's plane. Returns the fits
    ``(normal, offset, rms, inliers, centroid)`` and the distances of the last assignment."""
    for _ in range(2):
        dist = np.stack([np.abs(pts @ n + d) for n, d in side_planes], axis=1)  # [N, S]
        near = dist.argmin(1)
        second = np.sort(dist, axis=1)[:, 1] if dist.shape[1] > 1 else np.full(len(pts), np.inf)
        band = SETTINGS.inlier_band * thr
        clean = (dist.min(1) < band) & (second > band)
        fits = []
        for k, (n0, d0) in enumerate(side_planes):
            idx = clean & (near == k)
            if idx.sum() < SETTINGS.refit_min_points:
                fits.append((n0, d0, np.nan, 0, pts[near == k].mean(0) if (near == k).any() else None))
                continue
            n, d, rms = _lsq_plane(pts[idx])
            if n @ n0 < 0:
                n, d = -n, -d
            fits.append((n, d, rms, int(idx.sum()), pts[idx].mean(0)))
        side_planes = [(f[0], f[1]) for f in fits]
    return fits, dist


def _axis_normal(fits, ks: list[int], side_axis, gi: int, fallback: np.ndarray) -> np.ndarray:
    if not ks:
        ks_all = [k for k in range(len(fits)) if side_axis[k] == gi]
        nav = fits[ks_all[0]][0] if ks_all else fallback
    else:
        ref = fits[ks[0]][0]
        nav = np.mean([fits[k][0] * np.sign(fits[k][0] @ ref) for k in ks], axis=0)
    return nav / np.linalg.norm(nav)


def _faces_per_axis(fits, side_axis, groups, planes, centre0: np.ndarray, size: float):
    """Per direction: its mean normal, its faces (signed position at the face points' centroid) and the
    edge between two opposite faces. Returns ``(faces, edge_per_axis, axis_normals, axis_centres)``."""
    best_count = max(f[3] for f in fits)
    faces: list[dict] = []
    edge_per_axis: list[float | None] = []
    axis_normals = []
    axis_centres: list[float | None] = []
    for gi in range(len(groups)):
        least = max(SETTINGS.plane_min_points, SETTINGS.face_min_share * best_count)
        ks = [k for k in range(len(fits)) if side_axis[k] == gi and fits[k][3] >= least]
        nav = _axis_normal(fits, ks, side_axis, gi, planes[groups[gi][0]][0])
        axis_normals.append(nav)
        offs = []
        for k in ks:
            _, _, rms, cnt, c = fits[k]
            pos = float(nav @ c)
            outward = nav if pos > nav @ centre0 else -nav
            faces.append({"axis": gi, "normal": outward, "offset": pos, "inliers": cnt, "rms": float(rms)})
            offs.append(pos)
        if len(offs) == 2 and abs(offs[0] - offs[1]) > 0.5 * size:
            edge_per_axis.append(float(abs(offs[0] - offs[1])))
            axis_centres.append(float(np.mean(offs)))
        else:
            edge_per_axis.append(None)
            axis_centres.append(None)
    return faces, edge_per_axis, axis_normals, axis_centres


def _cube_centre(axes: np.ndarray, axis_centres, faces, edge: float, centre0: np.ndarray) -> np.ndarray:
    """The mid-plane where both faces are known, else one face moved by edge/2 inward, else the mean."""
    coords = []
    for ax in range(3):
        if axis_centres[ax] is not None:
            coords.append(axis_centres[ax])
            continue
        one = [f for f in faces if f["axis"] == ax]
        if one:
            f = one[0]
            sign = 1.0 if f["normal"] @ axes[ax] > 0 else -1.0
            coords.append(f["offset"] - sign * edge / 2)
        else:
            coords.append(float(axes[ax] @ centre0))
    return np.linalg.solve(axes, np.array(coords))


def fit_cube_planes(
    points: np.ndarray,
    size_hint: float | None = None,
    threshold: float | None = None,
    max_planes: int = 8,
    iterations: int = 1000,
    seed: int = 0,
) -> CubeFit | None:
    """Fit the cube's face planes and measure its edge. ``points [N, 3]`` are the cube's points.

    ``threshold`` (RANSAC inlier distance) defaults to 2 % of the edge (``size_hint`` or the robust
    OBB size). Returns None when fewer than one pair of opposite faces could be fitted.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < SETTINGS.fit_min_points:
        return None
    if size_hint:
        size = float(size_hint)
    else:
        _, lo, hi, _ = _robust_obb(pts)
        size = float(np.mean(hi - lo))
    thr = float(threshold) if threshold else SETTINGS.plane_threshold * size
    planes = _ransac_planes(pts, thr, max_planes, iterations, seed)
    if len(planes) < 2:
        return None
    planes = _refine_planes(pts, planes, thr)
    _, near, ok = _nearest_plane(pts, planes, thr)
    counts = np.array([int((ok & (near == k)).sum()) for k in range(len(planes))])
    groups = _group_directions(planes, counts)
    side_axis, side_planes = _side_planes(pts, planes, groups, counts, near, ok, size)
    fits, dist = _final_face_fits(pts, side_planes, thr)
    ok = dist.min(1) < SETTINGS.inlier_band * thr
    centre0 = pts.mean(0)
    faces, edge_per_axis, axis_normals, axis_centres = _faces_per_axis(fits, side_axis, groups, planes, centre0, size)
    measured = [e for e in edge_per_axis if e is not None]
    if not measured:
        return None
    edge = float(np.mean(measured))
    # orthonormal axes closest to the fitted normals (SVD), completing a missing third axis
    A = np.array(axis_normals)
    if len(A) == 1:
        return None
    if len(A) == 2:
        A = np.vstack([A, np.cross(A[0], A[1])])
        edge_per_axis.append(None)
        axis_centres.append(None)
    u, _, vt = np.linalg.svd(A)
    axes = u @ vt
    centre = _cube_centre(axes, axis_centres, faces, edge, centre0)
    plane_rms = float(np.sqrt(np.mean(dist.min(1)[ok] ** 2))) if ok.sum() else float("nan")
    fit = CubeFit(
        edge=edge, edge_per_axis=edge_per_axis, axes=axes, centre=centre, faces=faces, plane_rms=plane_rms
    )
    fit.extra["face_points"] = _face_counts(pts, fit, thr)
    return fit


def _face_counts(pts: np.ndarray, fit: CubeFit, thr: float) -> dict[str, int]:
    """Points within the inlier band of each of the six ideal faces, keyed ``'{axis}{+|-}'``."""
    rel = (pts - fit.centre) @ fit.axes.T  # [N, 3]
    h = fit.edge / 2
    out = {}
    for ax in range(3):
        inside = np.all(np.abs(np.delete(rel, ax, axis=1)) < h * SETTINGS.face_reach, axis=1)
        for sgn, name in ((1, "+"), (-1, "-")):
            out[f"{ax}{name}"] = int((inside & (np.abs(rel[:, ax] - sgn * h) < SETTINGS.inlier_band * thr)).sum())
    return out


def decide_up(
    fit: CubeFit,
    camera_centres: np.ndarray | None = None,
    reference_up: np.ndarray | None = None,
) -> CubeFit:
    """Choose which cube axis (and sign) is "up" and store it in ``fit`` (see the module docstring).

    ``reference_up`` (e.g. +z of an ArUco-calibrated frame) picks the cube axis closest to it.
    """
    cands = [(ax, s) for ax in range(3) for s in (1.0, -1.0)]
    if reference_up is not None:
        r = np.asarray(reference_up, float) / np.linalg.norm(reference_up)
        ax, s = max(cands, key=lambda c: c[1] * (fit.axes[c[0]] @ r))
        fit.up_axis, fit.up, fit.up_method, fit.up_confident = ax, s * fit.axes[ax], "reference frame", True
        return fit
    if camera_centres is not None and len(camera_centres) >= 3:
        cams = np.asarray(camera_centres, float)
        scores = []
        for ax, s in cands:
            u = s * fit.axes[ax]
            h = (cams - (fit.centre - u * fit.edge / 2)) @ u  # heights above the candidate ground
            scores.append((float(np.mean(h > 0)), float(np.median(h)), ax, s))
        scores.sort(reverse=True)
        best = scores[0]
        fit.up_axis, fit.up = best[2], best[3] * fit.axes[best[2]]
        fit.up_method = f"cameras ({best[0]:.0%} above the ground)"
        fit.up_confident = best[0] >= SETTINGS.up_camera_share and scores[1][0] < SETTINGS.up_camera_share
        return fit
    fc = fit.extra.get("face_points", {})
    best = None
    for ax in range(3):
        a, b = fc.get(f"{ax}+", 0), fc.get(f"{ax}-", 0)
        hi, lo = max(a, b), min(a, b)
        ratio = lo / max(hi, 1)
        s = 1.0 if a > b else -1.0  # the well-seen face is the top, the unseen one the bottom
        if best is None or ratio < best[0]:
            best = (ratio, ax, s)
    ratio, ax, s = best
    fit.up_axis, fit.up = ax, s * fit.axes[ax]
    fit.up_method = f"unseen bottom face (its point count is {ratio:.0%} of the top's)"
    fit.up_confident = ratio < SETTINGS.up_bottom_ratio
    return fit


def use_envelope(fit: CubeFit, points: np.ndarray, q: float = 0.01) -> CubeFit:
    """Measure the cube by the envelope of its points instead of its faces' planes (in place).

    A Gaussian-splat reconstruction fills the inside of an opaque face with Gaussians (only the
    outermost layer is seen), so the least-squares planes through a face's Gaussians lie inside the
    face: on synthetic captures with known cubes, 0.2-0.4 cm per face, a 10 cm cube measuring 9.2-9.6
    cm. The outer envelope is unbiased: along each fitted axis the edge is the extent between the
    ``q`` and ``1 - q`` quantiles of ``points [N, 3]`` (the cube cluster, best with the Gaussians'
    extents sampled), and the centre is that extent's midpoint (the hidden bottom face is bounded by
    the side faces reaching the ground). The planes' values stay in ``fit.extra``.

    Example:
        >>> from plantsplat.cube import cube_surface_points
        >>> rng = np.random.default_rng(0)
        >>> pts = cube_surface_points(10.0, 6000, rng, faces=("+x", "-x", "+y", "-y", "top"))
        >>> fit = use_envelope(fit_cube_planes(pts, size_hint=10.0), pts, q=0.0)
        >>> round(fit.edge, 2), fit.extra["edge_method"]
        (10.0, 'envelope')
    """
    proj = np.asarray(points, dtype=np.float64) @ fit.axes.T  # [N, 3] coordinates along the cube axes
    lo, hi = np.quantile(proj, [q, 1.0 - q], axis=0)  # [3], [3]
    fit.extra.update({"edge_planes": fit.edge, "edge_per_axis_planes": list(fit.edge_per_axis),
                      "edge_method": "envelope", "envelope_quantile": q})
    fit.edge_per_axis = [float(e) for e in hi - lo]
    fit.edge = float(np.mean(hi - lo))
    fit.centre = np.linalg.solve(fit.axes, (lo + hi) / 2.0)
    return fit


def cube_frame_transform(fit: CubeFit, cube_size: float) -> tuple[np.ndarray, float]:
    """The similarity that maps the cloud into the calibrated frame: ``(T [4, 4], scale)`` with
    ``x_cm = scale * R (x - bottom_centre)``; z along ``up``, x along the first other cube axis."""
    assert fit.up is not None and fit.up_axis is not None
    z = fit.up
    xa = [a for a in range(3) if a != fit.up_axis][0]
    x = fit.axes[xa] - (fit.axes[xa] @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows
    s = cube_size / fit.edge
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = -s * R @ fit.bottom_centre
    return T, float(s)

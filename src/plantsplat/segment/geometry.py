"""Multi-view geometry from the marker cube: intrinsics, per-frame cube pose, cube silhouette, orbit
centre and a coarse visual hull of the plant.

A phone video carries no intrinsics, but the cube's markers are a non-planar calibration target with
known 3D corners: a focal-length search (minimising the multi-marker PnP reprojection error) gives a
starting point and OpenCV's ``calibrateCamera`` refines it over every frame with markers. With the
intrinsics, :func:`plantsplat.cube.cube_pose` gives each frame's camera pose in the cube frame
(cm, z up, origin on the ground under the cube), which is a world frame because the cube does not
move. Short gaps (frames whose markers are hidden) are bridged by interpolating the camera pose.

Example:
    >>> K, dist, info = estimate_intrinsics(detections, (540, 960))
    >>> poses, rms, how = cube_poses(detections, K, dist)
    >>> hull = cube_silhouette(poses[0], K, dist, (540, 960))   # bool [960, 540]
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

import numba
import numpy as np
from numba import njit, prange

from plantsplat.cube import CubeSpec, cube_pose
from plantsplat.log import get_logger

# OpenMP first, as the rasterizer's modules: the TBB that some wheels bring is too old for numba and would only
# print a warning
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

log = get_logger(__name__)


def _pose_errors(dets: list[dict[int, np.ndarray]], K: np.ndarray, cube: CubeSpec) -> float:
    errs = []
    for d in dets:
        r = cube_pose(d, K, None, cube)
        if r is not None:
            errs.append(r[1])
    return float(np.median(errs)) if errs else np.inf


def estimate_intrinsics(
    detections: list[dict[int, np.ndarray]],
    image_size: tuple[int, int],
    cube: CubeSpec = CubeSpec(),
    max_views: int = 40,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | None:
    """Pinhole intrinsics from the cube's marker corners over many frames.

    ``detections``: per frame ``{marker_id: corners [4, 2]}``; ``image_size``: ``(width, height)``.
    The principal point is fixed at the image centre, pixels are square and distortion is zero
    (phone videos are distortion-corrected in camera). Returns ``(K [3, 3], dist [5], info)`` or
    ``None`` when fewer than 3 frames show markers.

    Example:
        >>> K, dist, info = estimate_intrinsics(dets, (540, 960))
        >>> round(K[0, 0])      # focal length in pixels
        731
    """
    import cv2

    w, h = image_size
    views = [d for d in detections if d]
    if len(views) < 3:
        return None
    multi = [d for d in views if len(d) >= 2]
    pool = multi if len(multi) >= 3 else views
    rng = np.random.default_rng(0)
    sample = [pool[i] for i in sorted(rng.choice(len(pool), size=min(len(pool), 24), replace=False))]

    def K_of(f):
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], dtype=np.float64)

    # coarse log-spaced search (on half the sample), then golden-section refinement of the median reprojection error
    fs = np.geomspace(0.3, 4.0, 28) * max(w, h)
    errs = [_pose_errors(sample[::2], K_of(f), cube) for f in fs]
    i = int(np.argmin(errs))
    lo, hi = fs[max(i - 1, 0)], fs[min(i + 1, len(fs) - 1)]
    g = (np.sqrt(5) - 1) / 2
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    ec, ed = _pose_errors(sample, K_of(c), cube), _pose_errors(sample, K_of(d), cube)
    for _ in range(6):  # the bracket (two grid steps, 20 % of f) shrinks to 5.6 % of itself; calibrateCamera refines below
        if ec < ed:
            b, d, ed = d, c, ec
            c = b - g * (b - a)
            ec = _pose_errors(sample, K_of(c), cube)
        else:
            a, c, ec = c, d, ed
            d = a + g * (b - a)
            ed = _pose_errors(sample, K_of(d), cube)
    f0 = (a + b) / 2
    K = K_of(f0)
    info: dict[str, Any] = {"method": "focal search", "focal_search": round(float(f0), 3),
                            "views": len(views), "multi_marker_views": len(multi)}
    # refine over many views (all marker corners at once)
    use = pool if len(pool) <= max_views else [pool[i] for i in np.linspace(0, len(pool) - 1, max_views).astype(int)]
    obj = [np.concatenate([cube.marker_corners(i) for i in sorted(d)]).astype(np.float32) for d in use]
    img = [np.concatenate([d[i] for i in sorted(d)]).astype(np.float32) for d in use]
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    try:
        rms, K1, _, _, _ = cv2.calibrateCamera(obj, img, (w, h), K.copy(), np.zeros(5), flags=flags)
        if np.isfinite(rms) and 0.25 * f0 < K1[0, 0] < 4 * f0 and rms < 5.0:
            K = K1
            info.update(method="calibrateCamera", rms_px=round(float(rms), 4))
    except cv2.error as exc:  # degenerate views: keep the search result
        info["calibrate_error"] = str(exc).splitlines()[0][:120]
    info["fx"] = round(float(K[0, 0]), 3)
    return K, np.zeros(5), info


def cube_poses(
    detections: list[dict[int, np.ndarray]],
    K: np.ndarray,
    dist: np.ndarray | None = None,
    cube: CubeSpec = CubeSpec(),
    max_rms: float = 3.0,
    max_gap: int = 3,
    max_step_deg: float = 20.0,
) -> tuple[list[np.ndarray | None], list[float | None], list[str]]:
    """Per-frame ``T_cam_cube [4, 4]`` from markers; short gaps bridged by interpolating the camera.

    Frames whose markers fit worse than ``max_rms`` pixels are treated as undetected. A run of at
    most ``max_gap`` frames without a pose between two frames with one gets an interpolated pose
    (slerp of the rotation, linear camera centre) when the camera turned less than ``max_step_deg``
    between them. Returns ``(poses, rms, how)`` with ``how`` in
    ``{"markers", "interpolated", "none"}``.
    """
    n = len(detections)
    poses: list[np.ndarray | None] = [None] * n
    rms: list[float | None] = [None] * n
    how = ["none"] * n
    for i, d in enumerate(detections):
        r = cube_pose(d, K, dist, cube) if d else None
        if r is not None and r[1] <= max_rms:
            poses[i], rms[i], how[i] = r[0], r[1], "markers"
    filled = interpolate_gaps(poses, max_gap, max_step_deg)
    for j in range(n):
        if poses[j] is None and filled[j] is not None:
            poses[j], how[j] = filled[j], "interpolated"
    return poses, rms, how


def interpolate_gaps(
    poses: list[np.ndarray | None], max_gap: int = 3, max_step_deg: float = 20.0
) -> list[np.ndarray | None]:
    """Fill runs of at most ``max_gap`` missing poses between two known ones (slerp + linear centre).

    A run is filled only when the camera turned less than ``max_step_deg`` between the two ends.
    """
    from scipy.spatial.transform import Rotation, Slerp

    out = list(poses)
    have = [i for i in range(len(poses)) if poses[i] is not None]
    for a, b in zip(have[:-1], have[1:]):
        if not 1 < b - a <= max_gap + 1:
            continue
        ca, cb = np.linalg.inv(poses[a]), np.linalg.inv(poses[b])  # camera-to-cube
        turn = np.degrees(Rotation.from_matrix(ca[:3, :3].T @ cb[:3, :3]).magnitude())
        if turn > max_step_deg:
            continue
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([ca[:3, :3], cb[:3, :3]])))
        for j in range(a + 1, b):
            t = (j - a) / (b - a)
            c2w = np.eye(4)
            c2w[:3, :3] = slerp([t]).as_matrix()[0]
            c2w[:3, 3] = (1 - t) * ca[:3, 3] + t * cb[:3, 3]
            out[j] = np.linalg.inv(c2w)
    return out


def project(points: np.ndarray, T_cam_world: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points ``[N, 3]`` -> pixels ``[N, 2]`` and depths ``[N]``."""
    pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]  # [N, 3]
    z = pc[:, 2]
    uv = (pc @ K.T)[:, :2] / np.maximum(z, 1e-6)[:, None]
    return uv, z


def cube_silhouette(
    T_cam_cube: np.ndarray, K: np.ndarray, dist: np.ndarray | None, size: tuple[int, int], cube: CubeSpec = CubeSpec()
) -> np.ndarray:
    """Exact silhouette of the whole cube (all 6 faces) in one frame: bool ``[H, W]``.

    The cube is convex, so its silhouette is the convex hull of its 8 projected vertices (drawn with
    1/16-pixel precision).
    """
    import cv2

    w, h = size
    out = np.zeros((h, w), np.uint8)
    corners = cube.corners()  # [8, 3]
    pc = corners @ T_cam_cube[:3, :3].T + T_cam_cube[:3, 3]
    if np.any(pc[:, 2] <= 1e-3):
        return out.astype(bool)  # the camera is inside / behind the cube: nothing sensible to draw
    rvec = cv2.Rodrigues(T_cam_cube[:3, :3])[0]
    uv, _ = cv2.projectPoints(corners, rvec, T_cam_cube[:3, 3], K, np.zeros(5) if dist is None else dist)
    hull = cv2.convexHull(uv.reshape(-1, 2).astype(np.float32))
    cv2.fillConvexPoly(out, np.round(hull.reshape(-1, 2) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def cube_appearance(
    T_cam_cube: np.ndarray, K: np.ndarray, dist: np.ndarray | None, size: tuple[int, int], cube: CubeSpec = CubeSpec(),
    texels: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """How the cube should look in one frame: its printed faces drawn with the camera.

    Each face facing the camera is a white square with its ArUco marker centred; it is mapped into the
    image by the homography of its projected corners. Returns ``(expected float32 [H, W]`` in [0, 1]
    (0 = black print, 1 = white), ``face int8 [H, W]`` (index into :data:`plantsplat.cube.FACE_NAMES`,
    -1 off the cube)). Comparing a frame with it shows where something stands in front of the cube.
    """
    import cv2

    from plantsplat.cube import FACE_NAMES, marker_image

    w, h = size
    expected = np.zeros((h, w), np.float32)
    face_map = np.full((h, w), -1, np.int8)
    R, t = T_cam_cube[:3, :3], T_cam_cube[:3, 3]
    cam = -R.T @ t
    rvec = cv2.Rodrigues(R)[0]
    m = int(round(texels * cube.marker_size / cube.size))
    off = (texels - m) // 2
    for k, name in enumerate(FACE_NAMES):
        c, n, r, u = cube.face_frame(name)
        if float(n @ (cam - c)) <= 1e-6:
            continue  # seen from behind
        hs = cube.size / 2
        quad3 = np.array([c - r * hs + u * hs, c + r * hs + u * hs, c + r * hs - u * hs, c - r * hs - u * hs])
        if np.any((quad3 @ R.T + t)[:, 2] <= 1e-3):
            continue
        uv, _ = cv2.projectPoints(quad3, rvec, t, K, np.zeros(5) if dist is None else dist)
        tex = np.full((texels, texels), 255, np.uint8)
        tex[off:off + m, off:off + m] = marker_image(cube.face_ids[k], m, cube)
        src = np.array([[-0.5, -0.5], [texels - 0.5, -0.5], [texels - 0.5, texels - 0.5], [-0.5, texels - 0.5]],
                       np.float32)
        H = cv2.getPerspectiveTransform(src, uv.reshape(4, 2).astype(np.float32))
        q = uv.reshape(4, 2)
        bx0, by0 = max(0, int(np.floor(q[:, 0].min())) - 1), max(0, int(np.floor(q[:, 1].min())) - 1)
        bx1, by1 = min(w, int(np.ceil(q[:, 0].max())) + 2), min(h, int(np.ceil(q[:, 1].max())) + 2)
        if bx1 <= bx0 or by1 <= by0:
            continue
        Hb = np.array([[1, 0, -bx0], [0, 1, -by0], [0, 0, 1]], np.float64) @ H  # into the face's box
        size_b = (bx1 - bx0, by1 - by0)
        warped = cv2.warpPerspective(tex, Hb, size_b, flags=cv2.INTER_LINEAR, borderValue=0)
        inside = cv2.warpPerspective(np.ones((texels, texels), np.uint8), Hb, size_b, flags=cv2.INTER_NEAREST,
                                     borderValue=0).astype(bool)
        expected[by0:by1, bx0:bx1][inside] = warped[inside] / 255.0
        face_map[by0:by1, bx0:bx1][inside] = k
    return expected, face_map


def align_cube(rgb: np.ndarray, expected: np.ndarray, face_map: np.ndarray, max_shift: float = 0.5,
               min_score: float = 0.35) -> tuple[np.ndarray, np.ndarray, tuple[float, float]] | None:
    """Shift the drawn cube onto the cube in the frame (a camera interpolated along the orbit is a few pixels off).

    Finds the translation of the expected print that best matches the frame's gray (normalised
    cross-correlation over the cube's box grown by ``max_shift`` of its size, masked to the faces),
    refined to sub-pixel by OpenCV's ECC. Returns ``(expected, face_map, (dx, dy))`` shifted, or None when
    the best match scores under ``min_score`` (the cube is hidden or not there).
    """
    import cv2

    on = face_map >= 0
    if on.sum() < 64:
        return None
    ys, xs = np.nonzero(on)
    bw, bh = xs.max() - xs.min() + 1, ys.max() - ys.min() + 1
    m = int(np.ceil(max_shift * max(bw, bh)))
    H, W = face_map.shape
    x0, x1 = max(0, xs.min() - m), min(W, xs.max() + m + 1)
    y0, y1 = max(0, ys.min() - m), min(H, ys.max() + m + 1)
    gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)[y0:y1, x0:x1].astype(np.float32)
    bx0, bx1, by0, by1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    tmpl = (expected[by0:by1, bx0:bx1] * 255).astype(np.float32)
    tmask = on[by0:by1, bx0:bx1].astype(np.float32)
    if gray.shape[0] < tmpl.shape[0] or gray.shape[1] < tmpl.shape[1]:
        return None
    # global search first (the error can exceed ECC's reach), then sub-pixel ECC from the best offset
    score = cv2.matchTemplate(gray, tmpl, cv2.TM_CCOEFF_NORMED, mask=tmask)
    score[~np.isfinite(score)] = -1
    _, best, _, (px, py) = cv2.minMaxLoc(score)
    dx, dy = float(px + x0 - bx0), float(py + y0 - by0)
    if best < min_score:
        return None
    crop_t = (expected[y0:y1, x0:x1] * 255).astype(np.float32)
    mask = on[y0:y1, x0:x1].astype(np.uint8)
    try:
        _, warp = cv2.findTransformECC(crop_t, gray, np.array([[1, 0, dx], [0, 1, dy]], np.float32),
                                       cv2.MOTION_TRANSLATION,
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 1e-4), mask, 3)
        if np.hypot(warp[0, 2] - dx, warp[1, 2] - dy) < 3:
            dx, dy = float(warp[0, 2]), float(warp[1, 2])
    except cv2.error:
        pass
    if np.hypot(dx, dy) > max_shift * max(bw, bh):
        return None
    A = np.array([[1, 0, dx], [0, 1, dy]], np.float32)
    exp2 = cv2.warpAffine(expected, A, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)
    faces2 = cv2.warpAffine(face_map.astype(np.int16), A, (W, H), flags=cv2.INTER_NEAREST, borderValue=-1).astype(np.int8)
    return exp2, faces2, (dx, dy)


def faces_shown(rgb: np.ndarray, expected: np.ndarray, face_map: np.ndarray, min_ncc: float = 0.1) -> np.ndarray:
    """``face_map`` without the faces whose print the frame does not show: int8 ``[H, W]``, -1 there too.

    A face counts when the frame's gray levels over the whole face correlate with its drawn print (normalised
    cross-correlation at least ``min_ncc``). A face hidden behind something (a pot of any colour) does not correlate,
    while the per-pixel test of :func:`cube_occluded` can be fooled there: an occluder of the print's white (or black)
    matches that half of the pattern. Partly hidden faces still correlate. Used for frames whose camera is borrowed
    (interpolated along the orbit), where nothing else says the cube is in view: on three synthetic captures (seeds
    1, 3, 4 of the segmentation benchmark) the faces such frames drew over the pot held 108k wrong pixels, the faces
    it drops 10k cube pixels (my script).
    """
    import cv2

    out = face_map.copy()
    if not (face_map >= 0).any():
        return out
    gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float64)
    for k in np.unique(face_map[face_map >= 0]):
        f = face_map == k
        e, g = expected[f].astype(np.float64), gray[f]
        if e.std() < 1e-3 or g.std() < 1e-3 or float(np.corrcoef(e, g)[0, 1]) < min_ncc:
            out[f] = -1
    return out


def cube_occluded(rgb: np.ndarray, expected: np.ndarray, face_map: np.ndarray, min_contrast: float = 15.0,
                  tolerance: float = 0.45) -> np.ndarray:
    """Pixels of the cube's faces where the frame does not show the printed pattern: bool ``[H, W]``.

    Per face the black and white print levels are low and high percentiles of the gray where the pattern is dark
    and light (robust to much of the face being hidden);
    a pixel whose (slightly blurred) gray differs from the pattern's by more than ``tolerance`` of that
    contrast, or that is clearly coloured (the print is black and white), shows something in front of
    the cube (the pot, a leaf, a hand). A face whose print shows less than ``min_contrast`` gray levels
    of contrast is hidden altogether. Isolated mismatches along print edges (pose error of a pixel or
    two) are ignored: only mismatches covering most of a small neighbourhood count.
    """
    import cv2

    out = np.zeros(face_map.shape, bool)
    on = face_map >= 0
    if not on.any():
        return out
    ys, xs = np.nonzero(on)  # work in the cube's box (grown for the filters)
    y0, y1 = max(0, ys.min() - 8), min(on.shape[0], ys.max() + 9)
    x0, x1 = max(0, xs.min() - 8), min(on.shape[1], xs.max() + 9)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1])
    fmap, expc = face_map[y0:y1, x0:x1], expected[y0:y1, x0:x1]
    gray = cv2.GaussianBlur(cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY).astype(np.float32), (5, 5), 1.5)
    exp_b = cv2.GaussianBlur(np.ascontiguousarray(expc), (5, 5), 1.5)
    sat = cv2.cvtColor(crop, cv2.COLOR_RGB2HSV)[..., 1]
    bad = np.zeros(gray.shape, np.float32)
    for k in np.unique(fmap[fmap >= 0]):
        f = fmap == k
        dark = f & (expc < 0.2)
        light = f & (expc > 0.8)
        if dark.sum() < 8 or light.sum() < 8:
            bad[f] = 1.0
            continue
        lo, hi = float(np.percentile(gray[dark], 20)), float(np.percentile(gray[light], 80))
        if hi - lo < min_contrast:
            bad[f] = 1.0
            continue
        pred = lo + (hi - lo) * exp_b
        mism = (np.abs(gray - pred) > tolerance * (hi - lo)) | ((sat > 100) & (gray > 40))
        bad[f] = mism[f].astype(np.float32)
    onf = (fmap >= 0).astype(np.float32)  # the share is taken over face pixels only (no ring left at the border)
    out[y0:y1, x0:x1] = (cv2.blur(bad, (7, 7)) > 0.6 * np.maximum(cv2.blur(onf, (7, 7)), 1e-6)) & (onf > 0)
    return out


def orbit_centre(poses: list[np.ndarray | None]) -> np.ndarray | None:
    """The 3D point closest (least squares) to every camera's optical axis: what the camera circles. ``[3]``."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    n = 0
    for T in poses:
        if T is None:
            continue
        c2w = np.linalg.inv(T)
        c, d = c2w[:3, 3], c2w[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
        n += 1
    if n < 3 or np.linalg.cond(A) > 1e8:
        return None
    return np.linalg.solve(A, b)


@njit(parallel=True, cache=True)
def _carve(xyz, P, M, keep, seen, hit):  # pragma: no cover - numba
    """Per voxel (xyz [3, V] float32), in the views' order: how many views see it (seen) and how many of those
    have it in their mask (hit), projecting with P [F, 3, 4] into the masks M [F, h, w] (uint8 0/1). From the
    9th view on, every 4th view, a voxel stops as soon as it can no longer reach the keep fraction (its counts
    are then final: it is not kept)."""
    nf = P.shape[0]
    h = M.shape[1]
    w = M.shape[2]
    for vi in prange(xyz.shape[1]):
        x = xyz[0, vi]
        y = xyz[1, vi]
        zc = xyz[2, vi]
        s = 0
        ht = 0
        for step in range(nf):
            z = P[step, 2, 0] * x + P[step, 2, 1] * y + P[step, 2, 2] * zc + P[step, 2, 3]
            zs = max(z, np.float32(1e-6))
            u = np.rint((P[step, 0, 0] * x + P[step, 0, 1] * y + P[step, 0, 2] * zc + P[step, 0, 3]) / zs)
            v = np.rint((P[step, 1, 0] * x + P[step, 1, 1] * y + P[step, 1, 2] * zc + P[step, 1, 3]) / zs)
            if z > np.float32(1e-3) and u >= 0 and u < w and v >= 0 and v < h:
                s += 1
                ht += M[step, int(v), int(u)]
            if step >= 8 and step % 4 == 0:
                remaining = nf - step - 1
                ok = (ht + remaining) >= keep * (s + remaining)
                if not ok or (s >= 8 and (s - ht) > (1 - keep) * (s + remaining) + 1):
                    break
        seen[vi] = s
        hit[vi] = ht


def visual_hull(
    masks: list[np.ndarray | None],
    poses: list[np.ndarray | None],
    K: np.ndarray,
    centre: np.ndarray,
    radius: float,
    z_range: tuple[float, float],
    voxels: int = 72,
    keep_fraction: float = 0.6,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Carve a voxel grid with per-frame foreground masks (bool ``[h, w]``, ``K`` for that size).

    The grid spans ``centre.xy +- radius`` and ``z_range`` (cube frame, cm). A voxel is kept when it
    projects into the mask in at least ``keep_fraction`` of the frames that see it (and it is seen by
    at least 3 frames); the tolerance absorbs occlusion by the pot and pose errors. Returns
    ``(occupied bool [X, Y, Z], origin [3], voxel size)``.
    """
    vs = 2 * radius / voxels
    nz = max(2, int(np.ceil((z_range[1] - z_range[0]) / vs)))
    origin = np.array([centre[0] - radius, centre[1] - radius, z_range[0]]) + vs / 2
    # voxel centres [3, V], V in (x, y, z) C order, written axis by axis (no [V, 3] index and float64 copies)
    xyz = np.empty((3, voxels, voxels, nz), np.float32)
    xyz[0] = (origin[0] + np.arange(voxels) * vs).astype(np.float32)[:, None, None]
    xyz[1] = (origin[1] + np.arange(voxels) * vs).astype(np.float32)[None, :, None]
    xyz[2] = (origin[2] + np.arange(nz) * vs).astype(np.float32)[None, None, :]
    xyz = xyz.reshape(3, -1)
    order = [i for i in range(len(masks)) if masks[i] is not None and poses[i] is not None]
    order = [order[i] for i in np.random.default_rng(0).permutation(len(order))]
    seen = np.zeros(xyz.shape[1], np.int32)
    hit = np.zeros(xyz.shape[1], np.int32)
    if order:
        P = np.stack([(K @ poses[fi][:3]).astype(np.float32) for fi in order])  # [F, 3, 4] projection matrices
        M = np.stack([np.asarray(masks[fi], dtype=bool) for fi in order]).view(np.uint8)  # [F, h, w]
        _carve(xyz, P, M, float(keep_fraction), seen, hit)
    occ = (seen >= 3) & (hit >= keep_fraction * np.maximum(seen, 1))
    return occ.reshape(voxels, voxels, nz), origin, vs


def plant_component(
    occ: np.ndarray, origin: np.ndarray, vs: float, axis_xy: np.ndarray, axis_radius: float, gap: float
) -> np.ndarray:
    """The plant in a carved grid: components near the orbit axis plus those within ``gap`` cm of them.

    Green objects elsewhere in the room are separate components away from the axis and are dropped.
    Returns bool ``[X, Y, Z]``.
    """
    from scipy import ndimage

    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3)))
    if n == 0:
        return occ
    X, Y, _ = occ.shape
    xs = origin[0] + np.arange(X) * vs
    ys = origin[1] + np.arange(Y) * vs
    d2 = (xs[:, None] - axis_xy[0]) ** 2 + (ys[None, :] - axis_xy[1]) ** 2  # [X, Y]
    near_axis = np.broadcast_to((d2 <= axis_radius**2)[:, :, None], occ.shape)
    sizes = ndimage.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
    near = np.unique(lab[near_axis & occ])
    near = near[near > 0]
    if len(near) == 0:
        # nothing on the axis: take the largest component closest to it
        com = ndimage.center_of_mass(occ, lab, index=np.arange(1, n + 1))
        dist = [np.hypot(origin[0] + c[0] * vs - axis_xy[0], origin[1] + c[1] * vs - axis_xy[1]) for c in com]
        near = np.array([1 + int(np.argmin(np.asarray(dist) - 1e-3 * sizes))])
    keep = np.isin(lab, near)
    r = max(1, int(round(gap / vs)))
    struct = ndimage.generate_binary_structure(3, 1)
    while True:
        grown = ndimage.binary_dilation(keep, structure=struct, iterations=r)
        add = np.unique(lab[grown & occ & ~keep])
        add = add[add > 0]
        if len(add) == 0:
            break
        keep |= np.isin(lab, add)
    return keep


def poses_from_features(
    grays: list[np.ndarray],
    poses: list[np.ndarray | None],
    K: np.ndarray,
    window: int = 4,
    min_inliers: int = 15,
    max_features: int = 2000,
) -> tuple[list[np.ndarray | None], list[bool]]:
    """Camera poses for frames without a cube pose, from SIFT matches with nearby posed frames.

    Frames are taken nearest-to-a-posed-frame first. For a frame ``j`` without a pose, the two
    nearest frames with a pose (within ``window`` frames; frames located here count) are matched with SIFT (ratio test); the matches are triangulated with their known cameras, and
    ``j`` is located by RANSAC PnP on its matches to those 3D points. ``grays``: gray uint8 frames
    ``[h, w]``, ``K`` for that size. Returns the completed pose list and a flag per frame (True =
    pose found here). Poses are checked: enough inliers, sub-2-px refined error, and a camera centre
    no farther from its nearest neighbour's than the camera moves per frame there.
    """
    import cv2

    n = len(poses)
    sift = cv2.SIFT_create(nfeatures=max_features)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    feats: dict[int, tuple] = {}

    def features(i):
        if i not in feats:
            kp, des = sift.detectAndCompute(grays[i], None)
            pts = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
            feats[i] = (pts, des)
        return feats[i]

    def matches(i, j):
        (pi, di), (pj, dj) = features(i), features(j)
        if di is None or dj is None or len(di) < 8 or len(dj) < 8:
            return np.zeros((0, 2), np.int64)
        out = []
        for m in matcher.knnMatch(di, dj, k=2):
            if len(m) == 2 and m[0].distance < 0.75 * m[1].distance:
                out.append((m[0].queryIdx, m[0].trainIdx))
        return np.array(out, np.int64).reshape(-1, 2)

    def P(T):
        return K @ T[:3, :]

    result = list(poses)
    found = [False] * n
    # frames nearest to posed ones first; frames located here serve as references for the rest
    todo = sorted((j for j in range(n) if poses[j] is None),
                  key=lambda j: min((abs(i - j) for i in range(n) if poses[i] is not None), default=n))
    for j in todo:
        posed = [i for i in range(n) if result[i] is not None]
        near = sorted((abs(i - j), i) for i in posed if 0 < abs(i - j) <= window)
        if len(near) < 2:
            continue
        a, b = near[0][1], near[1][1]
        mab = matches(a, b)
        if len(mab) < min_inliers:
            continue
        pa, pb = features(a)[0][mab[:, 0]], features(b)[0][mab[:, 1]]
        X = cv2.triangulatePoints(P(result[a]), P(result[b]), pa.T, pb.T)
        X = (X[:3] / X[3:]).T  # [M, 3]
        ok = np.ones(len(X), bool)
        for T, p in ((result[a], pa), (result[b], pb)):
            uv, z = project(X, T, K)
            ok &= (z > 0) & (np.linalg.norm(uv - p, axis=1) < 2.0)
        point_of_a = {int(k): X[m] for m, k in enumerate(mab[:, 0]) if ok[m]}
        point_of_b = {int(k): X[m] for m, k in enumerate(mab[:, 1]) if ok[m]}
        obj, img = [], []
        pj = features(j)[0]
        for other, table in ((a, point_of_a), (b, point_of_b)):
            for qi, ti in matches(j, other):
                if int(ti) in table:
                    obj.append(table[int(ti)])
                    img.append(pj[qi])
        if len(obj) < min_inliers:
            continue
        obj_a, img_a = np.array(obj, np.float64), np.array(img, np.float64)
        okp, rvec, tvec, inl = cv2.solvePnPRansac(obj_a, img_a, K, None, reprojectionError=3.0, iterationsCount=300,
                                                  confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if not okp or inl is None or len(inl) < min_inliers:
            continue
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj_a[inl], img_a[inl], K, None, rvec, tvec)
        proj, _ = cv2.projectPoints(obj_a[inl], rvec, tvec, K, None)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_a[inl]) ** 2, axis=1))))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = np.asarray(tvec).ravel()
        c = np.linalg.inv(T)[:3, 3]
        ca, cb = np.linalg.inv(result[a])[:3, 3], np.linalg.inv(result[b])[:3, 3]
        step = np.linalg.norm(ca - cb) / abs(a - b)  # camera travel per frame around here
        if err > 2.0 or np.linalg.norm(c - ca) > 1.2 * step * abs(a - j) + 1.0:
            continue
        result[j], found[j] = T, True
    return result, found


def fill_orbit_poses(
    poses: list[np.ndarray | None], centre: np.ndarray, max_extrapolate: int = 12
) -> tuple[list[np.ndarray | None], list[bool]]:
    """A camera pose for every frame of an orbit: gaps interpolated along the orbit, ends extrapolated.

    The capture is a smooth orbit around the vertical (z) axis through ``centre`` and frames come in
    video order. A missing camera between two posed frames ``a < j < b`` gets its centre interpolated
    in cylindrical coordinates about that axis (angle unwrapped, radius and height linear: the camera
    stays on the orbit instead of cutting the chord) and its orientation by slerp. Frames before the
    first / after the last posed frame (at most ``max_extrapolate`` away) are the nearest posed camera
    turned about the axis by the angle the camera travels per frame there. ``poses``: ``T_cam_world
    [4, 4]`` or None. Returns ``(poses, filled)`` (True = pose made here).

    Example:
        >>> full, filled = fill_orbit_poses([T0, None, None, T3], centre)   # T1, T2 on the orbit
    """
    from scipy.spatial.transform import Rotation, Slerp

    n = len(poses)
    out = list(poses)
    filled = [False] * n
    have = [i for i in range(n) if poses[i] is not None]
    if len(have) < 2:
        return out, filled
    c2w = {i: np.linalg.inv(poses[i]) for i in have}  # camera-to-world [4, 4]

    def cyl(p):  # camera centre -> (angle, radius, height) about the vertical axis through centre
        d = p[:2] - centre[:2]
        return np.arctan2(d[1], d[0]), np.hypot(d[0], d[1]), p[2]

    def from_cyl(a, r, z):
        return np.array([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), z])

    def rot_z(angle):
        c, s = np.cos(angle), np.sin(angle)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    def rate(i0, i1):  # mean turn per frame (rad) between two posed frames
        t0, t1 = cyl(c2w[i0][:3, 3])[0], cyl(c2w[i1][:3, 3])[0]
        return ((t1 - t0 + np.pi) % (2 * np.pi) - np.pi) / (i1 - i0)

    # turn per frame between consecutive posed frames whose turn is unambiguous (under a quarter turn)
    sure = [(m, rate(have[m], have[m + 1])) for m in range(len(have) - 1)]
    sure = [(m, w) for m, w in sure if abs(w) * (have[m + 1] - have[m]) < np.pi / 2]

    def local_rate(k):  # turn per frame around the gap after have[k]: the nearest sure pair on either side
        before = [w for m, w in sure if m < k]
        after = [w for m, w in sure if m > k]
        near = before[-1:] + after[:1]
        return float(np.mean(near)) if near else None

    for k, (a, b) in enumerate(zip(have[:-1], have[1:])):
        if b - a < 2:
            continue
        ta, ra, za = cyl(c2w[a][:3, 3])
        tb, rb, zb = cyl(c2w[b][:3, 3])
        dt = (tb - ta + np.pi) % (2 * np.pi) - np.pi  # shortest turn, [-pi, pi)
        w = local_rate(k)
        if w is not None:  # a long gap can turn the long way round, or more than once: follow the camera's pace
            dt += 2 * np.pi * np.round((w * (b - a) - dt) / (2 * np.pi))
        # orientations relative to the orbit (camera turned back by its angle), interpolated there and turned
        # forward again: the camera keeps facing the axis however far the gap turns
        rel = np.stack([rot_z(-ta) @ c2w[a][:3, :3], rot_z(-(ta + dt)) @ c2w[b][:3, :3]])
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(rel))
        for j in range(a + 1, b):
            t = (j - a) / (b - a)
            M = np.eye(4)
            M[:3, :3] = rot_z(ta + t * dt) @ slerp([t]).as_matrix()[0]
            M[:3, 3] = from_cyl(ta + t * dt, ra + t * (rb - ra), za + t * (zb - za))
            out[j], filled[j] = np.linalg.inv(M), True

    span = have[: min(len(have), 6)]
    w0 = rate(span[0], span[-1])
    span = have[-min(len(have), 6):]
    w1 = rate(span[0], span[-1])
    for j in range(n):
        if out[j] is not None:
            continue
        ref, w = (have[0], w0) if j < have[0] else (have[-1], w1)
        if abs(j - ref) > max_extrapolate:
            continue
        R = rot_z(w * (j - ref))
        M = np.eye(4)
        M[:3, :3] = R @ c2w[ref][:3, :3]
        M[:3, 3] = R @ (c2w[ref][:3, 3] - centre) + centre
        out[j], filled[j] = np.linalg.inv(M), True
    return out, filled


def fruit_sized(occ: np.ndarray, vs: float, max_cm: float) -> np.ndarray:
    """The pieces of a carved grid no thicker than a fruit: bool ``[X, Y, Z]``, the voxels of ``occ`` (bool, voxel
    size ``vs`` cm) in 26-connected pieces whose thickness (twice the largest distance from a voxel of the piece to
    its outside) is at most ``max_cm`` and whose longest side is at most twice that. A fruit's hull is a blob; fruit
    hanging side by side (a truss) make a longer piece, not a thicker one; a box, a pot or a slab of wall of fruit
    colour is thicker or longer.

    Example (a 4 cm blob is kept, a 12 cm rod of fruit colour is not):
        >>> occ = np.zeros((24, 24, 24), bool)
        >>> occ[2:6, 2:6, 2:6] = True
        >>> occ[8:20, 12:14, 12:14] = True
        >>> int(fruit_sized(occ, 1.0, 5.0).sum())
        64
    """
    from scipy import ndimage

    out = np.zeros(occ.shape, bool)
    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3)))
    for sl, k in zip(ndimage.find_objects(lab), range(1, n + 1)):
        piece = lab[sl] == k
        longest = max(x.stop - x.start for x in sl) * vs
        thick = 2.0 * float(ndimage.distance_transform_edt(np.pad(piece, 1)).max()) * vs
        if thick <= max_cm and longest <= 2.0 * max_cm:
            out[sl] |= piece
    return out


def find_pot(
    occ: np.ndarray, origin: np.ndarray, vs: float, min_radius: float = 3.0, min_fill: float = 0.7,
    max_base: float = 4.0, max_foot: float = 8.0, min_height: float = 4.0, rim_drop: float = 0.85, max_taper: float = 0.15,
    fat: float = 0.87
) -> dict[str, Any] | None:
    """A plant-coloured pot in a carved grid: the solid, disc-sectioned block standing on the ground.

    ``occ``: bool ``[X, Y, Z]`` voxels (cube frame, cm, z up, ground at z = 0), ``origin`` the centre of
    voxel ``(0, 0, 0)``, ``vs`` the voxel size. Leaves and stems are thin: their horizontal sections are
    sparse. A pot's sections are filled discs. The occupied column must start within ``max_base`` cm of
    the ground; the pot starts at its first section whose largest piece is a disc (equivalent radius at
    least ``min_radius`` cm, at least ``min_fill`` of that disc occupied), at most ``max_foot`` cm up
    (thinner sections below it are the pot's foot, narrowed by shadows and carving). Going up, the
    first section that is not a disc, is off the section below by more than half its radius (another
    object) or is narrower than ``rim_drop`` times the widest pot section below it (the crown above the
    rim) ends it. The frustum's radius is
    fitted to the lower 60 % of the pot (leaves and fruit hang around its upper part), its taper (radius
    gained per cm of height) limited to ``max_taper``, and made ``fat`` voxels thinner (carving views
    are dilated). Returns ``{"axis": [x, y], "z": (bottom, rim), "r": (r_bottom, r_rim)}`` (a
    frustum, cm) or None when there is no such block at least ``min_height`` cm high (pots that are not
    plant-coloured leave no block: nothing to remove).

    Example:
        >>> pot = find_pot(occ, origin, 1.1)
        >>> pot["z"][1]    # rim height, cm
        12.1
    """
    from scipy import ndimage

    X, Y, Z = occ.shape
    zs = origin[2] + np.arange(Z) * vs
    rows = []
    seen = False  # an occupied section above the ground
    for k in range(Z):
        sl = occ[:, :, k]
        if zs[k] <= -vs:  # below the ground: carving spill (shadows, table), not the pot
            continue
        if not sl.any():
            if rows:
                break
            if seen:
                return None  # a gap in the column below any pot section
            continue
        if not seen and zs[k] - vs / 2 > max_base:
            return None
        seen = True
        lab, n = ndimage.label(sl)
        sizes = ndimage.sum_labels(np.ones_like(lab), lab, index=np.arange(1, n + 1))
        big = lab == 1 + int(np.argmax(sizes))
        ij = np.argwhere(big).astype(np.float64)  # [P, 2]
        c = ij.mean(axis=0)
        r_eq = np.sqrt(len(ij) / np.pi)  # voxels
        gi, gj = np.meshgrid(np.arange(X), np.arange(Y), indexing="ij")
        disc = (gi - c[0]) ** 2 + (gj - c[1]) ** 2 <= r_eq**2
        fill = float((big & disc).sum() / max(disc.sum(), 1))
        disc_like = r_eq * vs >= min_radius and fill >= min_fill
        if not rows and not disc_like:
            if zs[k] - vs / 2 > max_foot:
                return None  # a thin column standing on the ground (stems), no pot
            continue  # the pot's foot, thinned by shadows and carving
        if not disc_like or (rows and r_eq * vs < rim_drop * max(r[3] for r in rows)):
            break  # not a filled disc, or narrower than the pot below: the plant's crown
        if rows and np.hypot(origin[0] + c[0] * vs - rows[-1][1], origin[1] + c[1] * vs - rows[-1][2]) > 0.5 * rows[-1][3]:
            break  # a different object at this height (fruit hanging beside the column), not the pot's next section
        rows.append((zs[k], origin[0] + c[0] * vs, origin[1] + c[1] * vs, r_eq * vs))
    if not rows:
        return None
    a = np.array(rows)  # [S, 4] z, x, y, r
    z0, z1 = a[0, 0] - vs / 2, a[-1, 0] + vs / 2
    if z1 - z0 < min_height:
        return None
    # the radius comes from the lower part of the pot (foliage and fruit hang around its upper part and fatten
    # the hull there), leaving out the foot narrowed near the ground, with the taper of common pots at most
    low = a[a[:, 0] <= z0 + 0.6 * (z1 - z0)]
    low = low[int(np.argmax(low[:, 3] >= 0.8 * low[:, 3].max())):]
    if len(low) >= 3:
        slope, icpt = np.polyfit(low[:, 0], low[:, 3], 1)
        slope = float(np.clip(slope, 0.0, max_taper))
        icpt = float(np.mean(low[:, 3] - slope * low[:, 0]))
    else:
        slope, icpt = 0.0, float(low[:, 3].mean())
    # the hull is about a voxel fatter than the pot (views are dilated before carving)
    r0, r1 = slope * z0 + icpt - fat * vs, slope * z1 + icpt - fat * vs
    # the pot stands on the ground; its frustum reaches a little below it (pose and carving errors)
    return {"axis": [float(np.median(a[:, 1])), float(np.median(a[:, 2]))], "z": (float(min(z0, -1.5 * vs)), float(z1)),
            "r": (float(max(r0, 0.5)), float(max(r1, 0.5)))}


def pot_inside(points: np.ndarray, pot: dict[str, Any], margin: float = 0.0) -> np.ndarray:
    """Which points ``[N, 3]`` lie in the pot frustum (grown by ``margin`` cm): bool ``[N]``."""
    (z0, z1), (r0, r1) = pot["z"], pot["r"]
    t = np.clip((points[:, 2] - z0) / max(z1 - z0, 1e-6), 0, 1)
    r = r0 + t * (r1 - r0) + margin
    d = np.hypot(points[:, 0] - pot["axis"][0], points[:, 1] - pot["axis"][1])
    return (d <= r) & (points[:, 2] >= z0 - margin) & (points[:, 2] <= z1 + margin)


def pot_silhouette(pot: dict[str, Any], T_cam_world: np.ndarray, K: np.ndarray, size: tuple[int, int],
                   segments: int = 72) -> np.ndarray:
    """The pot frustum's silhouette in one frame (it is convex: hull of its projected rims). bool ``[H, W]``."""
    import cv2

    w, h = size
    out = np.zeros((h, w), np.uint8)
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    pts = []
    for z, r in zip(pot["z"], pot["r"]):
        pts.append(np.stack([pot["axis"][0] + r * np.cos(ang), pot["axis"][1] + r * np.sin(ang),
                             np.full_like(ang, z)], 1))
    P = np.concatenate(pts)  # [2S, 3]
    uv, z = project(P, T_cam_world, K)
    if np.any(z <= 1e-3):
        return out.astype(bool)
    hull = cv2.convexHull(uv.astype(np.float32))
    cv2.fillConvexPoly(out, np.round(hull.reshape(-1, 2) * 16).astype(np.int32), 1, shift=4)
    return out.astype(bool)


def orbit_outliers(poses: list[np.ndarray | None], centre: np.ndarray, factor: float = 4.0,
                   min_cm: float = 3.0, min_deg: float = 6.0, window: int = 6, keep: Collection[int] = (),
                   any_side: bool = False) -> list[int]:
    """Frames whose pose disagrees with the orbit through their neighbours (e.g. a flipped one-marker pose).

    Each posed frame is predicted from its nearest posed frame on either side or from the two nearest
    on one side, whichever pair is closer (at most ``window`` frames away; farther for a frame with no
    posed frame that near) with :func:`fill_orbit_poses`. The
    frame that differs most from its prediction, by more than ``factor`` times the median difference
    (and at least ``min_cm`` cm / ``min_deg`` degrees, both grown with the distance to the
    neighbours), is dropped, and the search repeats (at most a fifth of the frames). Frames in ``keep``
    (poses from two or more markers, which cannot flip) are never dropped: where the orbit is poorly
    sampled, the prediction is the worse of the two. With ``any_side`` every pair is tried and the one
    that agrees best counts: the first frame of a new ring, a step up from the last, is then predicted
    from the frames after it (for cameras that are all trusted alike, such as an SfM model's). Returns
    the dropped indices.

    Example:
        >>> bad = orbit_outliers(poses, centre)   # e.g. [58]
    """
    from scipy.spatial.transform import Rotation

    poses = list(poses)
    dropped: list[int] = []
    n_posed = sum(p is not None for p in poses)
    # a frame's difference from its prediction depends only on its own and its two neighbours' poses, none of
    # which change while they stay: computed once per (frame, neighbours) over the repeated searches
    cache: dict[tuple[int, int, int], tuple[float, float] | None] = {}
    while len(dropped) < n_posed // 5:
        have = [i for i in range(len(poses)) if poses[i] is not None]
        rows = []
        for k, i in enumerate(have):
            pairs: list[tuple[int, ...]] = []
            for reach in (window, len(poses)):  # an isolated frame (often one marker) is checked against farther ones
                left = [j for j in have[max(0, k - 2):k] if i - j <= reach]
                right = [j for j in have[k + 1:k + 3] if j - i <= reach]
                pairs = ([(left[-1], right[0])] if left and right else []) + ([tuple(left)] if len(left) == 2 else []) \
                    + ([tuple(right)] if len(right) == 2 else [])
                if pairs:
                    break
            if not pairs:
                continue
            if not any_side:  # the closest neighbours
                pairs = [min(pairs, key=lambda ab: max(abs(i - ab[0]), abs(i - ab[1])))]
            best = None
            for a, b in pairs:
                if (i, a, b) not in cache:
                    lo, hi = min(a, b, i), max(a, b, i)
                    sub: list[np.ndarray | None] = [None] * (hi - lo + 1)
                    sub[a - lo], sub[b - lo] = poses[a], poses[b]
                    pred = fill_orbit_poses(sub, centre, max_extrapolate=hi - lo)[0][i - lo]
                    if pred is None:
                        cache[(i, a, b)] = None
                    else:
                        ci, cp = np.linalg.inv(poses[i]), np.linalg.inv(pred)
                        cache[(i, a, b)] = (float(np.linalg.norm(ci[:3, 3] - cp[:3, 3])),
                                            float(np.degrees(Rotation.from_matrix(ci[:3, :3].T @ cp[:3, :3]).magnitude())))
                if cache[(i, a, b)] is None:
                    continue
                d, ang = cache[(i, a, b)]
                gap = max(abs(i - a), abs(i - b))
                grown = 1.0 + (gap - 1) / 2
                off = max(d / (min_cm * grown), ang / (min_deg * grown))
                if best is None or off < best[0]:
                    best = (off, (i, d, ang, gap))
            if best is not None:
                rows.append(best[1])
        if len(rows) < 5:
            break
        r = np.array(rows)
        md, ma = np.median(r[:, 1]), np.median(r[:, 2])
        grow = 1.0 + (r[:, 3] - 1) / 2
        excess = np.maximum(r[:, 1] / (max(factor * md, min_cm) * grow), r[:, 2] / (max(factor * ma, min_deg) * grow))
        excess[np.isin(r[:, 0].astype(np.int64), np.asarray(list(keep), np.int64))] = 0.0
        w = int(np.argmax(excess))
        if excess[w] <= 1.0:
            break
        poses[int(r[w, 0])] = None
        dropped.append(int(r[w, 0]))
    return dropped

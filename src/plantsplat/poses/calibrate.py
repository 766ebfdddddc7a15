"""Metric calibration of an SfM model with the ArUco cube: scale, gravity and origin.

The cube frame (see :mod:`plantsplat.cube`) is the world frame of every later stage: origin at the
centre of the cube's bottom face (on the ground plane), +z up, centimetres. Given a COLMAP model
(any scale, any orientation) and the markers detected in its frames, :func:`calibrate` estimates
the similarity ``cube_from_model`` (``x_cube = s R x_model + t``):

1. every marker corner seen in two or more registered frames is triangulated from the SfM
   cameras (LO-RANSAC, pixel reprojection error, so a bad detection in one frame is ignored);
2. a robust similarity (LO-RANSAC, then Umeyama on the inliers) maps the triangulated corners onto
   the corners of :class:`~plantsplat.cube.CubeSpec`;
3. the cube's pose in the model is refined by minimising the reprojection error of all detected
   marker corners in all frames (robust Huber loss, SfM cameras fixed); marker detections whose
   reprojection error stays above ``max_residual_px`` are rejected and the fit repeated.

The per-detection reprojection errors are also the model's consistency check: a split or wrong
model cannot make the cube reproject where its markers are detected in every frame.

Usage:
    det = read_markers(Path("ws/markers.json")).frames
    cal = calibrate(reconstruction, det)
    cal.scale, cal.median_residual_px, cal.consistent
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from plantsplat.cube import CubeSpec
from plantsplat.log import get_logger
from plantsplat.poses.sfm import final_ba_options

log = get_logger(__name__)

CUBE_BA_ITERATIONS = 50
"""Iterations of the bundle adjustment on the cube's corners."""


@dataclass
class Calibration:
    """Result of :func:`calibrate`: ``x_cube = scale * R @ x_model + t``."""

    scale: float
    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]
    median_residual_px: float
    """Median over detections of the RMS reprojection error of a marker's 4 corners (pixels)."""
    frames_with_markers: int
    detections_used: int
    detections_rejected: list = field(default_factory=list)  # [(frame name, marker id, rms px)]
    frame_residuals_px: dict = field(default_factory=dict)  # {frame name: rms px over its kept markers}
    inlier_ratio: float = 1.0
    consistent: bool = True

    def matrix(self) -> np.ndarray:
        """The 4x4 similarity ``cube_from_model``."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    def to_pycolmap(self):
        return pycolmap.Sim3d(self.scale, pycolmap.Rotation3d(self.R), self.t.reshape(3, 1))

    def summary(self) -> dict:
        return {
            "scale": self.scale,
            "R": self.R,
            "t": self.t,
            "matrix": self.matrix(),
            "median_residual_px": self.median_residual_px,
            "frames_with_markers": self.frames_with_markers,
            "detections_used": self.detections_used,
            "detections_rejected": [
                {"frame": n, "marker": int(m), "rms_px": round(float(e), 2)} for n, m, e in self.detections_rejected
            ],
            "inlier_ratio": self.inlier_ratio,
            "consistent": self.consistent,
        }


def _cam_matrices(rec, names: list[str]):
    """``{name: (cam_from_world [3, 4], camera)}`` for the registered images among ``names``."""
    out = {}
    for img in rec.images.values():
        if img.name in names and img.has_pose:
            out[img.name] = (np.asarray(img.cam_from_world().matrix()), rec.cameras[img.camera_id])
    return out


def _project(P: np.ndarray, camera, X: np.ndarray) -> np.ndarray:
    """Project world points ``X [N, 3]`` with ``P = cam_from_world [3, 4]``; returns pixels ``[N, 2]``."""
    Xc = X @ P[:, :3].T + P[:, 3]  # [N, 3]
    Xc[:, 2] = np.maximum(Xc[:, 2], 1e-9)  # behind the camera: huge residual instead of a crash
    return np.asarray(camera.img_from_cam(Xc, check_cheirality=False)).reshape(-1, 2)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with ``dst ~ s R src + t`` (Umeyama 1991). ``src, dst [N, 3]``."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean())
    return s, R, mu_d - s * R @ mu_s


def _triangulate_corners(obs, cams, cube: CubeSpec):
    """Each marker corner seen in >= 2 frames triangulated in the model. Returns ``(model_pts, cube_pts)``
    ``[P, 3]`` pairs (None when fewer than four)."""
    tri_opts = pycolmap.EstimateTriangulationOptions()
    tri_opts.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
    tri_opts.ransac.max_error = 4.0
    tri_opts.ransac.random_seed = 0
    model_pts, cube_pts = [], []
    for mid in sorted({m for _, m, _ in obs}):
        seen = [(n, c) for n, m, c in obs if m == mid]
        if len(seen) < 2:
            continue
        corners3 = cube.marker_corners(mid)  # [4, 3]
        poses = [pycolmap.Rigid3d(cams[n][0]) for n, _ in seen]
        cameras = [cams[n][1] for n, _ in seen]
        for k in range(4):
            pts = np.array([c[k] for _, c in seen], dtype=np.float64)  # [m, 2]
            try:
                res = pycolmap.estimate_triangulation(pts, poses, cameras, tri_opts)
            except Exception:  # degenerate geometry (all views from one place)
                res = None
            if res is None or int(np.sum(res["inliers"])) < 2:
                continue
            model_pts.append(np.asarray(res["xyz"]).ravel())
            cube_pts.append(corners3[k])
    if len(model_pts) < 4:
        return None, None
    return np.array(model_pts), np.array(cube_pts)


def _robust_similarity(model_pts: np.ndarray, cube_pts: np.ndarray, cube: CubeSpec):
    """Similarity model -> cube by RANSAC (threshold in centimetres, the cube's units), refitted on its
    inliers. Returns ``(s, R, t, geometric_ok)``: ok when the triangulated corners do form the cube."""
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 0.05 * cube.size
    ransac.random_seed = 0
    try:
        sim = pycolmap.estimate_sim3d_robust(model_pts, cube_pts, ransac)
    except Exception:
        sim = None
    if isinstance(sim, dict):
        sim = sim.get("tgt_from_src")
    if sim is not None:
        M = np.asarray(sim.matrix())  # [3, 4] = [sR | t]
        s0 = float(np.cbrt(np.linalg.det(M[:, :3])))
        R0, t0 = M[:, :3] / s0, M[:, 3]
    else:
        s0, R0, t0 = umeyama(model_pts, cube_pts)
    resid = np.linalg.norm((s0 * model_pts @ R0.T + t0) - cube_pts, axis=1)
    inl = resid < ransac.max_error
    if inl.sum() >= 4:
        s0, R0, t0 = umeyama(model_pts[inl], cube_pts[inl])
    return s0, R0, t0, bool(inl.sum() >= max(4, 0.5 * len(inl)))


class _CubeReprojection:
    """Reprojection residuals of the cube's marker corners for ``model_from_cube`` parameters
    ``p = [rotvec (3), t (3), log s]`` (``x_model = s R x_cube + t``)."""

    def __init__(self, obs, cams, cube: CubeSpec):
        self.obs, self.cams = obs, cams
        self.X = {mid: cube.marker_corners(mid) for mid in {m for _, m, _ in obs}}

    def residuals(self, p, use):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        s = np.exp(p[6])
        out = []
        for (n, mid, c), u in zip(self.obs, use):
            if not u:
                continue
            Xm = s * self.X[mid] @ R.T + p[3:6]
            out.append((_project(self.cams[n][0], self.cams[n][1], Xm) - c).ravel())
        return np.concatenate(out)

    def rms(self, p) -> np.ndarray:
        """``[D]`` reprojection RMS per detection (px)."""
        r = self.residuals(p, np.ones(len(self.obs), dtype=bool)).reshape(len(self.obs), 4, 2)
        return np.sqrt((r**2).sum(-1).mean(-1))

    def refine(self, p, max_residual_px: float):
        """Huber least squares, detections far above the median residual left out, up to three times."""

        use = np.ones(len(self.obs), dtype=bool)
        for _ in range(3):
            if use.sum() == 0:
                break
            p = least_squares(self.residuals, p, args=(use,), loss="huber", f_scale=1.0, x_scale="jac").x
            rms = self.rms(p)
            new_use = rms <= max(max_residual_px, 3.0 * float(np.median(rms)))
            new_use &= rms <= 5.0 * max_residual_px
            if np.array_equal(new_use, use):
                break
            use = new_use
        return p


def _params(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``model_from_cube`` parameters for the similarity cube_from_model ``(s, R, t)``."""
    sm, Rm = 1.0 / s, R.T
    return np.concatenate([Rotation.from_matrix(Rm).as_rotvec(), -sm * Rm @ t, [np.log(sm)]])


def calibrate(
    rec,
    detections: dict[str, dict[int, np.ndarray]],
    cube: CubeSpec = CubeSpec(),
    max_residual_px: float = 3.0,
    min_frames: int = 2,
) -> Calibration | None:
    """Estimate ``cube_from_model`` for the pycolmap Reconstruction ``rec`` from marker ``detections``.

    The marker corners are triangulated, a robust similarity maps them onto the cube, and the cube's pose
    is refined by reprojection over all detections.

    Returns ``None`` when fewer than ``min_frames`` registered frames show a marker or no marker
    corner can be triangulated consistently. ``consistent`` is False when the cube does not
    reproject onto its detections in most frames (a wrong or badly split model).
    """
    cams = _cam_matrices(rec, list(detections))
    obs = [(n, mid, c) for n, d in detections.items() if n in cams for mid, c in d.items()]
    frames = {n for n, _, _ in obs}
    if len(frames) < min_frames:
        return None
    model_pts, cube_pts = _triangulate_corners(obs, cams, cube)
    if model_pts is None:
        return None
    s0, R0, t0, geometric_ok = _robust_similarity(model_pts, cube_pts, cube)
    reproj = _CubeReprojection(obs, cams, cube)
    p = reproj.refine(_params(s0, R0, t0), max_residual_px)
    if not np.isfinite(p).all() or abs(np.log(np.exp(p[6]) * s0)) > np.log(2.0):
        # the refinement ran away (a wrong model): fall back to the direct fit, flagged inconsistent
        p = _params(s0, R0, t0)
        geometric_ok = False
    rms = reproj.rms(p)
    Rm, sm, tm = Rotation.from_rotvec(p[:3]).as_matrix(), float(np.exp(p[6])), p[3:6]
    s, R = 1.0 / sm, Rm.T
    t = -s * R @ tm
    kept = rms <= max_residual_px
    frame_res = {}
    for n in sorted(frames):
        e = [rms[i] for i, (name, _, _) in enumerate(obs) if name == n and kept[i]]
        if e:
            frame_res[n] = float(np.sqrt(np.mean(np.square(e))))
    ratio = float(kept.mean())
    med = float(np.median(rms))
    return Calibration(
        scale=float(s),
        R=R,
        t=np.asarray(t, dtype=np.float64),
        median_residual_px=med,
        frames_with_markers=len(frames),
        detections_used=int(kept.sum()),
        detections_rejected=[(n, mid, float(rms[i])) for i, (n, mid, _) in enumerate(obs) if not kept[i]],
        frame_residuals_px=frame_res,
        inlier_ratio=ratio,
        consistent=bool(geometric_ok and med <= max_residual_px and ratio >= 0.8),
    )


def scale_uncertainty(rec, detections: dict[str, dict[int, np.ndarray]], order: list[str], cube: CubeSpec = CubeSpec(),
                      max_residual_px: float = 3.0, groups: int = 8) -> dict:
    """How well the cube fixes the model's scale: a delete-one-group jackknife over the frames that see it.

    The frames with markers, in video ``order``, are cut into up to ``groups`` runs of consecutive frames
    (each run sees the cube from one side); the scale is estimated again without each run, and the spread
    of those estimates gives the standard error of the scale from all frames. Returns ``{"relative_se":
    float | None, "groups": int, "frames": int}``; ``relative_se`` (a fraction of the scale) is None when
    fewer than two runs of at least two frames see the cube: then nothing says how well the scale is known.
    """
    seen = [n for n in order if n in detections]
    g = min(groups, len(seen) // 2)
    out = {"relative_se": None, "groups": int(max(g, 0)), "frames": len(seen)}
    if g < 2:
        return out
    runs = np.array_split(np.array(seen), g)
    logs = []
    for run in runs:
        held = set(run.tolist())
        cal = calibrate(rec, {n: d for n, d in detections.items() if n not in held}, cube, max_residual_px)
        if cal is None:
            return out
        logs.append(np.log(cal.scale))
    logs = np.array(logs)
    out["relative_se"] = float(np.sqrt((g - 1) / g * np.sum((logs - logs.mean()) ** 2)))
    return out


def up_vector(cal: Calibration | None) -> np.ndarray | None:
    """The world's +z (gravity up) in the model's original frame, or None without calibration."""
    if cal is None:
        return None
    return cal.R.T @ np.array([0.0, 0.0, 1.0])


def refine_with_cube(rec, detections: dict, cal: Calibration, cube: CubeSpec = CubeSpec(), num_threads: int = 2,
                     within_px: float | None = None, refine_distortion: bool = True, loss_scale_px: float = 1.0) -> int:
    """Bundle adjustment of a model already in the cube frame, with the marker corners as control points.

    Every marker corner seen in two or more frames (detections kept by :func:`calibrate`) is added
    to ``rec`` as a 3D point held constant at its known position on the cube (cm), observed at its
    detected sub-pixel corners; cameras, intrinsics and the other points are refined together. The
    cube's metric geometry then constrains the focal length and scale along with the SfM tracks.
    ``within_px``: detections that :func:`calibrate` rejected but that lie within this many pixels
    are used too (for a model warped as a whole, whose residuals exceed the detections' own error).
    ``refine_distortion``: refine the lens distortion too (False keeps it as it is); ``loss_scale_px``: the Cauchy
    loss's scale on the reprojection errors (:func:`plantsplat.poses.sfm.final_ba_options`).
    Returns the number of control points added (0: nothing done).
    """
    rejected = {(n, m) for n, m, r in cal.detections_rejected if within_px is None or r > within_px}
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    tracks: dict[tuple[int, int], list] = {}
    for name, det in detections.items():
        im = by_name.get(name)
        if im is None:
            continue
        for mid, corners in det.items():
            if (name, mid) in rejected or cube.face_of(mid) is None:
                continue
            for k in range(4):
                tracks.setdefault((mid, k), []).append((im.image_id, corners[k]))
    tracks = {key: obs for key, obs in tracks.items() if len(obs) >= 2}
    if len(tracks) < 4:
        return 0
    # append the corner observations to each image's 2D points
    new_pts: dict[int, list] = {}
    for key, obs in tracks.items():
        for image_id, xy in obs:
            new_pts.setdefault(image_id, []).append((key, xy))
    index: dict[tuple[int, tuple[int, int]], int] = {}
    for image_id, items in new_pts.items():
        im = rec.images[image_id]
        base = len(im.points2D)
        for j, (key, xy) in enumerate(items):
            im.points2D.append(pycolmap.Point2D(np.asarray(xy, dtype=np.float64).reshape(2, 1)))
            index[(image_id, key)] = base + j
    ids = []
    for (mid, k), obs in tracks.items():
        track = pycolmap.Track()
        for image_id, _ in obs:
            track.add_element(image_id, index[(image_id, (mid, k))])
        ids.append(rec.add_point3D(cube.marker_corners(mid)[k].reshape(3, 1), track, np.array([255, 255, 255], np.uint8)))
    config = pycolmap.BundleAdjustmentConfig()
    for im in by_name.values():
        config.add_image(im.image_id)
    for pid in ids:
        config.add_constant_point(pid)
    opts = final_ba_options(refine_distortion, num_threads, loss_scale_px, CUBE_BA_ITERATIONS)
    adjuster = pycolmap.create_default_bundle_adjuster(opts, config, rec)
    adjuster.solve()
    return len(ids)

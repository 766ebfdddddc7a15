"""Compare estimated camera poses with reference poses (ground truth or another model).

Both sets are camera-to-world 4x4 matrices in OpenCV axes keyed by image name. A similarity
``ref ~ s R est + t`` is fitted to the camera centres (Umeyama); errors are reported after it:
rotation error (degrees, geodesic), camera-centre error (reference units). When both sets are
metric and in the same world frame (our cube frame and a synthetic capture's ground truth mapped
into its cube frame), the fitted similarity itself measures the calibration: ``scale_error_pct``
= ``|s - 1|`` in percent, ``up_error_deg`` = angle by which the fit tilts +z, ``origin_error``
= ``|t|``.

Example:
    >>> import numpy as np
    >>> T = {f"f{i}": np.eye(4) for i in range(3)}
    >>> for i, k in enumerate(T): T[k][:3, 3] = [i, i * i, 1.0]
    >>> compare_poses(T, T)["rotation_error_deg"]["median"]
    0.0
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plantsplat.poses.calibrate import umeyama
from plantsplat.poses.interop import OPENCV_TO_OPENGL, c2w_opencv, registered_images


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    return {"median": float(np.median(x)), "mean": float(np.mean(x)), "max": float(np.max(x))} if len(x) else {}


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def compare_poses(est: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict:
    """Pose errors of ``est`` against ``ref`` (camera-to-world 4x4, OpenCV axes) after a similarity fit.

    Only names present in both are compared; ``n_compared`` says how many.
    """
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        raise ValueError(f"need at least 3 common images to compare poses, got {len(names)}")
    Ce = np.array([np.asarray(est[n])[:3, 3] for n in names])  # [N, 3]
    Cr = np.array([np.asarray(ref[n])[:3, 3] for n in names])  # [N, 3]
    s, R, t = umeyama(Ce, Cr)
    centre_err = np.linalg.norm(s * Ce @ R.T + t - Cr, axis=1)  # [N]
    rot_err = np.array(
        [rotation_angle_deg(np.asarray(ref[n])[:3, :3].T @ R @ np.asarray(est[n])[:3, :3]) for n in names]
    )
    up = R @ np.array([0.0, 0.0, 1.0])
    return {
        "n_compared": len(names),
        "rotation_error_deg": _stats(rot_err),
        "centre_error": _stats(centre_err),
        "similarity": {"scale": float(s), "R": R.tolist(), "t": t.tolist()},
        "scale_error_pct": float(abs(s - 1.0) * 100.0),
        "up_error_deg": float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0)))),
        "frame_rotation_deg": rotation_angle_deg(R),
        "origin_error": float(np.linalg.norm(t)),
    }


def model_c2w(rec) -> dict[str, np.ndarray]:
    """``{name: camera-to-world 4x4}`` (OpenCV axes) of the registered images of a pycolmap model."""
    return {name: c2w_opencv(im) for name, im in registered_images(rec).items()}


def transforms_c2w(data: dict) -> dict[str, np.ndarray]:
    """``{file name: camera-to-world 4x4}`` (OpenCV axes) from a nerfstudio transforms dict."""
    return {
        Path(f["file_path"]).name: np.asarray(f["transform_matrix"], dtype=np.float64) @ OPENCV_TO_OPENGL
        for f in data["frames"]
    }


def cube_from_world(ground_truth: dict) -> np.ndarray:
    """The 4x4 similarity from a capture's true world frame to our cube frame (origin at the centre of the cube's
    bottom face, z up, cm). ``ground_truth``: a ``plantsplat synth`` ``ground_truth.json`` (``cube.T_world_cube``)
    or the foreign renders' (``calibration_cube.cube_to_world``, whose origin is the cube's centre)."""
    if "cube" in ground_truth:
        world_cube = np.asarray(ground_truth["cube"]["T_world_cube"], dtype=np.float64)
    else:
        cube = ground_truth["calibration_cube"]
        world_cube = np.asarray(cube["cube_to_world"], dtype=np.float64) @ np.array(
            [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -cube["edge_cm"] / 2], [0, 0, 0, 1.0]])
    return np.linalg.inv(world_cube)


def reference_cameras(ground_truth: dict, source_index: dict[str, int]) -> dict[str, np.ndarray]:
    """The true cameras of a capture with ground truth, for the workspace frames, in our cube frame.

    ``ground_truth``: a ``plantsplat synth`` ``ground_truth.json`` (``cube.T_world_cube``, whose frame is
    ours: origin at the centre of the cube's bottom face) or the foreign renders' format
    (``calibration_cube.cube_to_world`` with its origin at the cube's centre, ``frames[i].c2w``).
    ``source_index``: each workspace frame's video frame number (``frames.json``). Returns camera-to-world
    4x4 matrices (OpenCV axes, cm) by frame name.
    """
    cube_world = cube_from_world(ground_truth)
    frames = ground_truth["frames"]
    return {name: cube_world @ np.asarray(frames[i]["c2w"], dtype=np.float64) for name, i in source_index.items()}


def true_intrinsics(ground_truth: dict) -> np.ndarray:
    """The pinhole matrix ``K [3, 3]`` of a capture with ground truth (synth ``intrinsics`` or foreign ``camera.K``)."""
    if "intrinsics" in ground_truth:
        i = ground_truth["intrinsics"]
        return np.array([[i["fx"], 0.0, i["cx"]], [0.0, i["fy"], i["cy"]], [0.0, 0.0, 1.0]])
    return np.asarray(ground_truth["camera"]["K"], dtype=np.float64)


def object_scale(rec, ref: dict[str, np.ndarray], K: np.ndarray, radius: float = 30.0, min_views: int = 4) -> float | None:
    """Scale of a calibrated model near the object, against the truth: ``true / estimated`` (1 = right).

    Every SfM track seen in ``min_views`` frames is triangulated again from its raw pixels with the true
    cameras ``ref`` (camera-to-world, OpenCV axes) and intrinsics ``K`` (no distortion); the tracks
    within ``radius`` of the axis the cameras circle are fitted by a similarity (Umeyama on the 80 %
    that agree best) onto their true places. This is the scale that measurements of the plant and the
    cube inherit. The scale of a fit to the camera centres (:func:`compare_poses`) also holds how far
    the cameras were placed, which a focal length slightly off changes without changing the object.
    """
    P = {im.image_id: K @ np.linalg.inv(ref[im.name])[:3] for im in rec.images.values() if im.has_pose and im.name in ref}
    est, true = [], []
    for p in rec.points3D.values():
        rows = []
        for el in p.track.elements:
            if el.image_id in P:
                x, y = np.asarray(rec.images[el.image_id].points2D[el.point2D_idx].xy, dtype=np.float64)
                A = P[el.image_id]
                rows += [x * A[2] - A[0], y * A[2] - A[1]]
        if len(rows) >= 2 * min_views:
            X = np.linalg.svd(np.array(rows))[2][-1]
            est.append(p.xyz)
            true.append(X[:3] / X[3])
    if len(est) < 20:
        return None
    est, true = np.array(est), np.array(true)
    axis = np.mean([M[:2, 3] for M in ref.values()], axis=0)
    near = np.linalg.norm(true[:, :2] - axis, axis=1) < radius
    if near.sum() < 20:
        return None
    s, R, t = umeyama(est[near], true[near])
    res = np.linalg.norm(s * est[near] @ R.T + t - true[near], axis=1)
    keep = res <= np.percentile(res, 80)
    return float(umeyama(est[near][keep], true[near][keep])[0])


def synth_reference(ground_truth: dict) -> dict[str, np.ndarray]:
    """Ground-truth cameras of a ``plantsplat synth`` capture, in its cube frame (our world frame).

    ``ground_truth.json`` stores ``c2w`` in the synth world (origin below the pot); the cube stands at
    ``cube.T_world_cube``, so the reference in the cube frame is ``inv(T_world_cube) @ c2w``.
    """
    T_cube_world = np.linalg.inv(np.asarray(ground_truth["cube"]["T_world_cube"], dtype=np.float64))
    out = {}
    for f in ground_truth["frames"]:
        name = Path(f.get("file") or f.get("name")).name
        out[name] = T_cube_world @ np.asarray(f["c2w"], dtype=np.float64)
    return out

"""A second chance for frames the model left out: each is localised against the model's 3D points.

Frames the mappers could not register, or whose camera the path checks left out, often still share
many matches with registered frames whose keypoints the model triangulated. Those 2D-3D
correspondences give the frame's camera by robust absolute pose (LO-RANSAC, then refinement; the
shared camera's intrinsics held fixed): COLMAP's own registration step, run once per frame against
the model. A localised frame joins the model only when its pose is sure (as many inliers as the
mapper asks to register a frame) and its camera then lies on the path of its video neighbours; the
caller judges the latter.

Usage:
    poses = localize_frames(rec, db, ["frame_00012.png"], min_inliers=15)
    poses["frame_00012.png"]  # pycolmap.Rigid3d cam_from_world
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap


def _correspondences(d, rec, image_id: int, registered: dict[int, object]) -> tuple[np.ndarray, np.ndarray]:
    """2D keypoints of ``image_id`` and the model points their verified matches in registered frames see."""
    kp = np.asarray(d.read_keypoints(image_id))[:, :2]
    found: dict[int, int] = {}  # keypoint -> point3D id (the first match that sees one)
    for other_id, im in registered.items():
        n2d = len(im.points2D)
        if n2d == 0 or not d.exists_two_view_geometry(image_id, other_id):
            continue
        m = np.asarray(d.read_two_view_geometry(image_id, other_id).inlier_matches).reshape(-1, 2)  # [M, 2]: ours, theirs
        for k, j in m:
            if j >= n2d:  # a frame whose keypoints the model does not hold
                break
            p = im.points2D[int(j)]
            if p.has_point3D() and int(k) not in found:
                found[int(k)] = p.point3D_id
    keys = sorted(found)
    xyz = np.array([rec.points3D[found[k]].xyz for k in keys]).reshape(-1, 3)
    return kp[keys].reshape(-1, 2), xyz


def localize_frames(rec, db: Path, names: list[str], min_inliers: int) -> dict:
    """Camera poses (``cam_from_world``, pycolmap.Rigid3d) of the frames ``names`` localised against ``rec``'s
    points with at least ``min_inliers`` 2D-3D inliers; frames that cannot be localised so are absent."""
    cam = rec.cameras[next(iter(rec.cameras))]
    registered = {im.image_id: im for im in rec.images.values() if im.has_pose}
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.random_seed = 0
    refine = pycolmap.AbsolutePoseRefinementOptions()
    refine.refine_focal_length = False
    refine.refine_extra_params = False
    out = {}
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        for name in names:
            if name not in ids:
                continue
            xy, xyz = _correspondences(d, rec, ids[name], registered)
            if len(xy) < min_inliers:
                continue
            res = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, cam, opts, refine)
            if res is not None and int(res["num_inliers"]) >= min_inliers:
                out[name] = res["cam_from_world"]
    return out


def add_frames(rec, db: Path, poses: dict) -> list[str]:
    """Register the localised ``poses`` (name -> cam_from_world) in ``rec`` (frames without observations: their
    cameras only); returns the names added."""
    by_name = {im.name: im for im in rec.images.values()}
    cam_id = next(iter(rec.cameras))
    added = []
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
    for name, pose in poses.items():
        im = by_name.get(name)
        if im is None:
            rec.add_image_with_trivial_frame(pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=cam_id,
                                                            image_id=ids[name]), pose)
        else:
            rec.frames[im.frame_id].rig_from_world = pose
            rec.register_frame(im.frame_id)
        added.append(name)
    return added

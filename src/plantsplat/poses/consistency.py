"""Which verified image pairs a camera model contradicts: the pairs' own matches, checked against the model.

Two-view verification accepts a pair when enough of its matches fit *some* epipolar geometry. On
orbit captures of rooms with repeated texture (book spines, tiles, a poster seen twice) a few pairs
between frames that do not see the same surfaces pass with 15-25 inliers. Incremental mapping
trusts them like any other pair, and a handful of them can carry a stretch of the orbit off to a
wrong place: the frames of that stretch stay consistent with each other, but the pairs that link them
to their video neighbours no longer fit the model.

:func:`pair_errors` measures every verified pair under the model: the median Sampson distance (in
pixels) of the pair's inlier matches for the relative pose that the model gives the two cameras.
Right pairs of a right model sit near the keypoints' noise (well under a pixel to 1-2 px); a pair
that the model contradicts sits at tens of pixels. :func:`contradicted` lists those pairs; the poses
stage compares two mappers' models by them (:func:`contradiction`, and McNemar's test in
:mod:`plantsplat.poses.estimate`).

Example:
    >>> import numpy as np
    >>> K = np.eye(3)
    >>> R, t = np.eye(3), np.array([1.0, 0.0, 0.0])
    >>> X = np.array([[0.0, 0.0, 5.0], [1.0, 2.0, 6.0], [-1.0, 1.0, 4.0]])
    >>> xa = X[:, :2] / X[:, 2:]
    >>> xb = (X + t)[:, :2] / (X + t)[:, 2:]
    >>> [round(float(e), 9) + 0.0 for e in sampson_px(xa, xb, R, t, 1.0)]
    [0.0, 0.0, 0.0]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

MIN_PAIR_INLIERS = 15
"""Pairs with fewer verified inliers than this are not judged (COLMAP's mapper ignores them too)."""


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_px(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray, focal: float) -> np.ndarray:
    """Sampson distance (pixels) of normalised matches ``xa, xb [M, 2]`` for the relative pose ``x_b = R x_a + t``.

    ``focal`` turns the normalised-plane distance into pixels.
    """
    E = _skew(t / max(np.linalg.norm(t), 1e-12)) @ R  # [3, 3]
    ha = np.c_[xa, np.ones(len(xa))]  # [M, 3]
    hb = np.c_[xb, np.ones(len(xb))]
    Ea = ha @ E.T  # [M, 3]: epipolar lines in b
    Eb = hb @ E  # [M, 3]: epipolar lines in a
    num = np.sum(hb * Ea, axis=1) ** 2
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-24)) * focal


def pair_errors(rec, db: Path) -> dict[tuple[str, str], tuple[int, float]]:
    """Every verified pair of ``db`` whose frames are both registered in ``rec``:
    ``{(name_a, name_b): (inliers, median Sampson distance in pixels under the model)}``."""
    poses = {im.name: (np.asarray(im.cam_from_world().matrix()), rec.cameras[im.camera_id])
             for im in rec.images.values() if im.has_pose}
    out = {}
    with pycolmap.Database.open(str(db)) as d:
        names = {im.image_id: im.name for im in d.read_all_images()}
        pair_ids, geometries = d.read_two_view_geometries()
        keypoints: dict[int, np.ndarray] = {}
        for pid, geom in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            na, nb = names[a], names[b]
            m = np.asarray(geom.inlier_matches).reshape(-1, 2)
            if na not in poses or nb not in poses or len(m) < MIN_PAIR_INLIERS:
                continue
            for i in (a, b):
                if i not in keypoints:
                    keypoints[i] = np.asarray(d.read_keypoints(i))[:, :2]
            (Pa, cam_a), (Pb, cam_b) = poses[na], poses[nb]
            xa = np.asarray(cam_a.cam_from_img(keypoints[a][m[:, 0]]))
            xb = np.asarray(cam_b.cam_from_img(keypoints[b][m[:, 1]]))
            R = Pb[:, :3] @ Pa[:, :3].T
            t = Pb[:, 3] - R @ Pa[:, 3]
            err = sampson_px(xa, xb, R, t, float(np.mean([cam_a.mean_focal_length(), cam_b.mean_focal_length()])))
            out[(na, nb)] = (len(m), float(np.median(err)))
    return out


def contradicted(errors: dict[tuple[str, str], tuple[int, float]], max_px: float) -> list[tuple[str, str]]:
    """The pairs whose median Sampson distance under the model exceeds ``max_px``, worst first."""
    bad = [(p, e) for p, (_, e) in errors.items() if e > max_px]
    return [p for p, _ in sorted(bad, key=lambda x: -x[1])]


def contradiction(errors: dict[tuple[str, str], tuple[int, float]], max_px: float) -> float:
    """The share of the judged pairs' inlier matches that lie in pairs the model contradicts (0 = none)."""
    total = sum(n for n, _ in errors.values())
    bad = sum(n for n, e in errors.values() if e > max_px)
    return bad / total if total else 0.0

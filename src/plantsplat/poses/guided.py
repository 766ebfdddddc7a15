"""More matches where the model holds a frame weakly: its verified pairs matched again, guided.

A frame that sees little the others see (blurred, or mostly plant, whose repeated leaves fail the ratio test)
enters the model with a few dozen points, most of them made from it and one or two neighbours. Its camera can then
turn with those points: on one independent render a frame held by 51 points (the median frame: 158) came out turned
1.1 degrees about its optical axis, its neighbours 0.3. The pairs it verified know their two-view geometry; matched
again with each feature compared only with those near its epipolar line under that geometry (COLMAP's guided
matching), they keep the matches the ratio test dropped for a near-identical leaf elsewhere in the frame. Only the
weakly held frames' pairs are matched so, in a copy of the database from which the model's points are made the last
time: guided matching of every pair let wrong matches along the epipolar lines of repeated texture into the mapping
(another render's model came out with a frame 12 degrees off), and which frames are registered is decided from the
plain matches (:func:`plantsplat.poses.estimate.register`). The points the weak frames share with one other frame only
are left out of the model once it is adjusted (:func:`drop_weak_two_view`): a guided match along the epipolar line of
a repeated grain (the soil's) triangulates at the wrong depth with nothing to contradict it, and on one demo seed such
points below the soil made the height 8.7 % long; they have held the cameras in the adjustment, and nothing after
needs them.

Usage:
    weak = weakly_held(rec, names, 0.5)
    pairs = verified_pairs_with(db, weak)
    rematch_guided(db, work_dir / "database_guided.db", work_dir, pairs, cfg.sfm_options())
    # ... points made again from the guided copy, bundle-adjusted ...
    dropped = drop_weak_two_view(rec, weak)
"""

from __future__ import annotations

import contextlib
import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap

from plantsplat.poses.sfm import SfmConfig, copy_database, match_pairs


def weakly_held(rec, names: list[str], share: float) -> list[str]:
    """The frames of ``names`` registered in ``rec`` that see fewer of its points than ``share`` of the median
    registered frame does. Frames mapping left out are not among them: their pairs' geometry is what localising them
    must check, and guided matches along it let a wrong camera in (on one independent render, a frame 3.3 degrees
    off)."""
    counts = {im.name: im.num_points3D for im in rec.images.values() if im.has_pose}
    if not counts:
        return []
    floor = share * float(np.median(list(counts.values())))
    return [n for n in names if n in counts and counts[n] < floor]


def verified_pairs_with(db: Path, frames: list[str]) -> list[tuple[str, str]]:
    """The pairs of ``db`` with verified inliers that include one of ``frames``, in name order."""
    wanted = set(frames)
    with pycolmap.Database.open(str(db)) as d:
        names = {im.image_id: im.name for im in d.read_all_images()}
        pair_ids, geometries = d.read_two_view_geometries()
    out = []
    for pid, geom in zip(pair_ids, geometries):
        a, b = (names[i] for i in pycolmap.pair_id_to_image_pair(pid))
        if len(geom.inlier_matches) and (a in wanted or b in wanted):
            out.append((a, b))
    return sorted(out)


def pair_inliers(db: Path, pairs: list[tuple[str, str]]) -> int:
    """The verified inliers of ``pairs`` in ``db``, summed."""
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        return sum(len(d.read_two_view_geometry(ids[a], ids[b]).inlier_matches)
                   for a, b in pairs if d.exists_two_view_geometry(ids[a], ids[b]))


def rematch_guided(db: Path, guided_db: Path, work_dir: Path, pairs: list[tuple[str, str]], opts: SfmConfig) -> None:
    """``guided_db``: a copy of ``db`` in which ``pairs`` are matched and verified again (the same matches and geometry:
    seeded RANSAC), then matched once more with guided matching, whose inliers replace the pairs' verified ones."""
    copy_database(db, guided_db)
    with pycolmap.Database.open(str(guided_db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
    gone = [(int(pycolmap.image_pair_to_pair_id(ids[a], ids[b])),) for a, b in pairs]
    with contextlib.closing(sqlite3.connect(guided_db)) as c:
        for table in ("matches", "two_view_geometries"):
            c.executemany(f"DELETE FROM {table} WHERE pair_id = ?", gone)
        c.commit()
    match_pairs(guided_db, work_dir, pairs, dataclasses.replace(opts, guided_matching=True), "guided")


def drop_weak_two_view(rec, frames: list[str]) -> int:
    """Deletes from ``rec`` the points seen by two frames only, one of them among ``frames``; returns how many."""
    names = set(frames)
    weak = {im.image_id for im in rec.images.values() if im.name in names}
    gone = [pid for pid, p in rec.points3D.items()
            if p.track.length() == 2 and any(e.image_id in weak for e in p.track.elements)]
    for pid in gone:
        rec.delete_point3D(pid)
    return len(gone)

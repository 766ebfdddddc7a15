"""Fruit count: pieces of one fruit's red surface joined by what the frames show, separate fruit kept apart."""

from __future__ import annotations

import cv2
import numpy as np

from plantsplat.synth.camera import look_at
from plantsplat.train.data import View
from plantsplat.traits.config import TraitsConfig
from plantsplat.traits.fruit import count_fruit
from plantsplat.traits.fruit_views import candidate_pairs, joined_groups, judge_by_views, view_votes
from plantsplat.traits.stage import fruit_views
from plantsplat.workspace import Workspace

RED, GREEN = (200, 20, 25), (40, 120, 30)
SIZE, FOCAL = 400, 700.0


def _sphere(centre, radius, n=3000, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return np.asarray(centre) + radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def _camera(azimuth_deg, elevation_deg=25.0, distance=30.0):
    """World-to-camera (OpenCV axes) of a camera on a circle around the origin, looking at it."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    c = distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return np.linalg.inv(look_at(c, np.zeros(3)))


def _view(name, viewmat, fruit, occluder=None):
    """A frame of red ``fruit`` (a list of point sets), optionally crossed by a green bar through the projection of the
    point ``occluder`` (a petiole in front); the mask holds everything drawn."""
    K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]])
    img = np.full((SIZE, SIZE, 3), 90, np.uint8)
    for pts in fruit:
        X = pts @ viewmat[:3, :3].T + viewmat[:3, 3]
        uv = X @ K.T
        for u, v in np.round(uv[:, :2] / uv[:, 2:]).astype(int):
            cv2.circle(img, (int(u), int(v)), 2, RED, -1)
    if occluder is not None:
        X = viewmat[:3, :3] @ occluder + viewmat[:3, 3]
        u = int(round(FOCAL * X[0] / X[2] + SIZE / 2))
        cv2.rectangle(img, (u - 4, 0), (u + 4, SIZE - 1), GREEN, -1)
    mask = np.where(np.any(img != 90, axis=2), 255, 0).astype(np.uint8)
    return View(name=name, K=K, viewmat=viewmat, width=SIZE, height=SIZE, image=img, mask=mask)


def _cap(points, direction, degrees):
    """The points of a sphere around the origin within ``degrees`` of ``direction``: a patch of its surface."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    n = points / np.linalg.norm(points, axis=1, keepdims=True)
    return points[n @ d > np.cos(np.radians(degrees))]


def test_pieces_of_one_fruit_seen_past_a_petiole_are_one_fruit():
    fruit = _sphere([0, 0, 0], 1.5)
    pieces = [_cap(fruit, [0, -1, 0.3], 40), _cap(fruit, [0, 1, 0.3], 40)]  # the model lost the fruit between them
    assert candidate_pairs(pieces) == [(0, 1)]
    views = [_view(f"f{k}", _camera(30 * k), [fruit], occluder=np.zeros(3) if k in (0, 6) else None)
             for k in range(12)]
    one, two = view_votes(pieces, [(0, 1)], views, TraitsConfig())[(0, 1)]
    assert one >= 3 and two == 2  # the petiole splits the fruit in the two frames it crosses
    report: dict = {}
    judge = judge_by_views(lambda: views, TraitsConfig(), report)
    assert judge(pieces, np.eye(4)) == [0, 0]
    assert report["pairs"] == [{"pieces": [0, 1], "one": one, "two": two, "joined": True}]


def test_separate_fruit_side_by_side_stay_apart():
    a, b = _sphere([-1.3, 0, 0], 1.0, seed=1), _sphere([1.3, 0, 0], 1.0, seed=2)
    views = [_view(f"f{k}", _camera(30 * k), [a, b]) for k in range(12)]
    one, two = view_votes([a, b], [(0, 1)], views, TraitsConfig())[(0, 1)]
    assert two >= 3 and one == 0  # where one fruit stands before the other, the frame does not vote
    assert judge_by_views(lambda: views, TraitsConfig(), {})([a, b], np.eye(4)) == [0, 1]


def test_a_hidden_piece_gives_no_vote():
    fruit = _sphere([0, 0, 0], 1.5)
    hidden = _sphere([0, 0, 6.0], 1.0)  # not drawn in any frame: something hides it
    views = [_view(f"f{k}", _camera(30 * k), [fruit]) for k in range(4)]
    assert view_votes([fruit, hidden], [(0, 1)], views, TraitsConfig())[(0, 1)] == (0, 0)
    assert joined_groups(2, {(0, 1): (2, 0)}) == [0, 1]  # fewer frames than MIN_VIEWS decide nothing


def test_count_fruit_counts_joined_pieces_once():
    fruit = _sphere([0, 0, 10], 1.5)
    left, right = fruit[fruit[:, 0] < -0.4], fruit[fruit[:, 0] > 0.4]
    pts = np.vstack([left, right])
    cols = np.tile(np.array(RED, np.uint8), (len(pts), 1))
    n, centres = count_fruit(pts, cols, TraitsConfig())
    assert n == 2
    n, centres = count_fruit(pts, cols, TraitsConfig(), same_fruit=lambda pieces: [0] * len(pieces))
    assert n == 1 and np.allclose(centres[0], pts.mean(0))


def test_a_workspace_without_masks_has_no_fruit_views(tmp_path):
    assert fruit_views(Workspace(tmp_path / "plant")) is None
    report: dict = {}
    judge = judge_by_views(lambda: None, TraitsConfig(), report)
    pieces = [_sphere([0, 0, 0], 1.0)[:100], _sphere([0, 0, 0], 1.0)[100:200] + [2.2, 0, 0]]
    assert judge(pieces, np.eye(4)) == [0, 1] and "not checked" in report["note"]

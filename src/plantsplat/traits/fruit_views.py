"""Pieces of one fruit told from neighbouring fruit by what the frames show.

A ripe fruit deep in the crown is seen past petioles and leaves, so the model's red Gaussians on it can fall into
two or three pieces with gaps of 0.7-0.8 cm between them (demo seed 724, 2026-11-30: one fruit counted three
times). Separate fruit in a truss can lie as close (foreign render 103: two fruit 0.71 cm apart), so the gap
cannot tell the two cases apart. The frames can: seen from most directions, the pieces of one fruit fall in one
connected red region of the frame, and separate fruit fall in two.

Each pair of pieces that could be one fruit (the gap between them shorter than the smaller piece's extent) is
judged in every frame that shows both apart: a piece is shown when at least half of its points project onto
fruit-coloured pixels inside the frame's mask (otherwise something hides it), and the two are apart when the
convex outlines of their projections do not overlap (where one stands before the other, red joins them in the
frame whether they are one fruit or two). The pair votes "one" when the red region they fall in is the same
connected region, "two" otherwise. Pairs voting "one" in more frames than "two", in at least :data:`MIN_VIEWS`
frames, are joined.

Example:
    >>> joined_groups(3, {(0, 1): (8, 2), (1, 2): (1, 9)})
    [0, 0, 1]
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from plantsplat.train.data import project
from plantsplat.traits.config import TraitsConfig
from plantsplat.traits.fruit import fruit_mask

MIN_VIEWS = 3
"""Frames that must show both pieces of a pair before the frames decide it."""
SHOWN_SHARE = 0.5
"""A piece is shown in a frame when at least this share of its points in the frame land on fruit-coloured pixels."""
MASK_LEVEL = 127
"""Mask pixels above this are the object's (the masks are 0 / 255)."""


def candidate_pairs(pieces: Sequence[np.ndarray]) -> list[tuple[int, int]]:
    """Pairs ``(a, b)``, ``a < b``, of pieces ``[N_i, 3]`` whose gap (nearest points) is shorter than the smaller
    piece's longest extent: two pieces farther apart cannot be parts of one fruit's surface.

    Example:
        >>> a, b = np.array([[0, 0, 0], [2.0, 0, 0]]), np.array([[2.5, 0, 0], [4.0, 0, 0]])
        >>> candidate_pairs([a, b]), candidate_pairs([a, b + [5.0, 0, 0]])
        ([(0, 1)], [])
    """
    trees = [cKDTree(p) for p in pieces]
    size = [float(np.ptp(p, axis=0).max()) for p in pieces]
    out = []
    for a in range(len(pieces)):
        for b in range(a + 1, len(pieces)):
            gap = float(trees[a].query(pieces[b], k=1)[0].min())
            if gap < min(size[a], size[b]):
                out.append((a, b))
    return out


def red_regions(image: np.ndarray, mask: np.ndarray | None, s: TraitsConfig) -> np.ndarray:
    """``[H, W]`` int32: the connected (8-neighbour) regions of fruit-coloured pixels of ``image`` ``[H, W, 3]``
    (RGB) inside ``mask``, numbered from 1; 0 elsewhere. The colour model is applied to the mask's pixels only."""
    where = np.ones(image.shape[:2], bool) if mask is None else mask > MASK_LEVEL
    red = np.zeros(image.shape[:2], np.uint8)
    red[where] = fruit_mask(image[where], s)
    return cv2.connectedComponents(red, connectivity=8)[1]


def in_front(points: np.ndarray, view) -> np.ndarray:
    """``[M, 2]`` pixel positions in ``view`` of the points ``[N, 3]`` in front of its camera
    (:func:`plantsplat.train.data.project`)."""
    uv, z = project(points, view)
    return uv[z > 0]


def shown_region(uv: np.ndarray, regions: np.ndarray) -> int:
    """The red region (> 0) a piece projected at ``uv`` ``[M, 2]`` falls in; 0 when fewer than :data:`SHOWN_SHARE`
    of its points in the frame land on red pixels (hidden, or out of the frame)."""
    u, v = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
    h, w = regions.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if not inside.any():
        return 0
    hit = regions[v[inside], u[inside]]
    red = hit[hit > 0]
    if len(red) < SHOWN_SHARE * len(hit):
        return 0
    return int(np.bincount(red).argmax())


def overlap(uv_a: np.ndarray, uv_b: np.ndarray) -> bool:
    """Whether the convex outlines of two pieces' projections ``[M, 2]`` overlap: one stands before the other, so
    the frame cannot show whether red joins them."""
    hulls = [cv2.convexHull(np.ascontiguousarray(uv, np.float32)) for uv in (uv_a, uv_b)]
    if min(len(h) for h in hulls) < 3:
        return False
    return cv2.intersectConvexConvex(hulls[0], hulls[1])[0] > 0


def view_votes(pieces: Sequence[np.ndarray], pairs: list[tuple[int, int]], views: Sequence, s: TraitsConfig
               ) -> dict[tuple[int, int], tuple[int, int]]:
    """For each pair, ``(one, two)``: the frames showing both pieces apart (their outlines not overlapping) in one
    red region, and in two. ``views`` have ``image``, ``mask``, ``viewmat`` and ``K``
    (:class:`plantsplat.train.data.View`); the pieces are in their world frame."""
    votes = {p: [0, 0] for p in pairs}
    wanted = sorted({i for p in pairs for i in p})
    for view in views:
        regions = red_regions(view.image, view.mask, s)
        uv = {i: in_front(pieces[i], view) for i in wanted}
        shown = {i: shown_region(uv[i], regions) for i in wanted}
        for a, b in pairs:
            if shown[a] and shown[b] and not overlap(uv[a], uv[b]):
                votes[(a, b)][0 if shown[a] == shown[b] else 1] += 1
    return {p: (one, two) for p, (one, two) in votes.items()}


def joined_groups(n: int, votes: dict[tuple[int, int], tuple[int, int]]) -> list[int]:
    """Group number of each of ``n`` pieces, joining the pairs whose frames say "one" more often than "two" in at
    least :data:`MIN_VIEWS` frames (groups numbered by their first piece)."""
    joined = [(a, b) for (a, b), (one, two) in votes.items() if one + two >= MIN_VIEWS and one > two]
    edges = np.array(joined, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    labels = connected_components(graph, directed=False)[1]
    number = {g: k for k, g in enumerate(dict.fromkeys(labels.tolist()))}
    return [number[g] for g in labels.tolist()]


def judge_by_views(load_views: Callable[[], Sequence | None], s: TraitsConfig, report: dict
                   ) -> Callable[[list[np.ndarray], np.ndarray], list[int]]:
    """A function ``(pieces in cm, T model -> cm) -> group of each piece`` that asks the frames (loaded by
    ``load_views`` only when a pair is to be judged; None: no frames, every piece stays apart). What it decided goes
    into ``report`` (``pairs``: each judged pair with its votes and whether it was joined)."""

    def judge(pieces: list[np.ndarray], to_cm: np.ndarray) -> list[int]:
        pairs = candidate_pairs(pieces)
        if not pairs:
            return list(range(len(pieces)))
        views = load_views()
        if not views:
            report["note"] = "no frames with cameras and masks: fruit pieces were not checked against the frames"
            return list(range(len(pieces)))
        inv = np.linalg.inv(to_cm)
        in_model = [p @ inv[:3, :3].T + inv[:3, 3] for p in pieces]
        votes = view_votes(in_model, pairs, views, s)
        groups = joined_groups(len(pieces), votes)
        report["pairs"] = [{"pieces": [a, b], "one": one, "two": two, "joined": groups[a] == groups[b]}
                           for (a, b), (one, two) in sorted(votes.items())]
        return groups

    return judge

"""The plant decided in 3D with all the evidence, not with position alone: where, what colour, what it touches.

:func:`plantsplat.segment.object3d.object_model` gives the region the plant can be in (near the orbit's
axis, above the ground, in view of nearly every frame, near an SfM point, outside the pot and the
cube). A quick model can still put things there that are not plant: a patch of a blank wall drawn at
the wrong depth, a few Gaussians beside the cube. Four more kinds of evidence hold in any room:

- **appearance**, learned per capture from what geometry is sure of: the colours of the plant's
  body (below) where structure from motion found it (an SfM point within one neighbour spacing:
  texture seen from several frames), against the colours of the rest of the scene (the far room, the
  floor, the pot, the cube). Each candidate gets the log-likelihood ratio of its colour under the two
  (:func:`colour_evidence`). A patch of blank wall the quick model hangs against a leaf joins the body,
  but SfM finds nothing on it, so it does not teach the plant's colours the wall's;
- **attachment**: the plant is one body; the largest piece of candidates linked at a few centimetres
  is it (:func:`pieces`). A piece apart from it is less likely plant the farther it is:
  its prior falls with the square of the gap, measured against the body's size, so a leaf whose
  petiole the quick model lost or a fruit hanging over the pot's rim stays unless its colour is the
  room's, while a patch of wall above the plant or a clump by the cube, far from the body, goes;
- **support**: structure from motion puts points on the plant's textured surfaces; how near the body's
  Gaussians lie to them is learned per capture (:func:`support_reach`). A piece apart from the body none
  of whose Gaussians is that near an SfM point is held by nothing the frames agree on (a few Gaussians
  a quick model hangs in front of a blank wall): its prior is turned against it, so only a colour
  that is clearly the plant's keeps it. Where the caller says position cannot vouch even for the body
  (``needs_support``: over a pot's soil, which a quick model blurs into layers joined to the crown), each
  Gaussian there must be that near an SfM point itself;
- **neighbours**: a Gaussian takes the label of its neighbours in 3D unless their colours differ (a
  Potts term on the k-nearest-neighbour graph of the candidates, weighted as GrabCut weights
  neighbouring pixels), so a white flower on a green plant in a white room stays with its plant.
  The labels are the minimum cut of that graph (:func:`min_cut_labels`, scipy's maximum flow).

Usage:
    plant, facts = decide_plant(mu, rgb, opacity, candidates, background, orbit_radius, sfm_distance)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, maximum_flow
from scipy.spatial import cKDTree

HISTOGRAM_FLOOR = 1e-3
"""Every bin of a colour histogram gets this share of the mean bin's weight, so that a colour one model has not seen
keeps a small likelihood under it."""
BODY_SIZE_PERCENTILE = 95
"""The plant body's size: this percentile of its points' distances from their median (stray points aside)."""
MIN_COLOUR_SAMPLES = 50
"""The plant's colours are learned from its whole body where fewer of its Gaussians than this have an SfM point near."""
SUPPORT_PERCENTILE = 95
"""A piece apart from the body is held by an SfM point when one of its Gaussians lies as near one as this percentile of
the body's Gaussians do."""


@dataclass
class DecideConfig:
    """Weights of the evidence in the 3D decision (in nats: natural-log probability ratios)."""

    enabled: bool = True
    """Weigh colour and neighbours; False: the plant is every Gaussian in its region (position alone)."""
    sure_opacity: float = 0.5
    """Only Gaussians at least this opaque teach the colour models."""
    colour_bins: int = 16
    """Bins per RGB channel of the colour histograms (each smoothed by one bin)."""
    prior_log_odds: float = 2.0
    """How much more likely a candidate joined to the plant's body is plant than not, before its colour is seen."""
    gap_scale: float = 0.5
    """A piece apart from the body loses ``(gap / (gap_scale * body size))**2`` nats of that prior (a Gaussian prior on
    the gap; the body's size is its 95th-percentile distance from its middle)."""
    max_colour_evidence: float = 4.0
    """The colour's log-likelihood ratio is clipped to this (a colour neither model has seen decides nothing)."""
    neighbours: int = 8
    """Neighbours of each candidate in the body graph."""
    smoothness: float = 1.5
    """Cost of cutting between two neighbours of the same colour at the typical neighbour distance."""
    teach_reach: float = 1.0
    """Only the body's Gaussians within this many typical neighbour distances of an SfM point teach the plant's colours
    (0: the whole body)."""
    attach_reach: float = 0.07
    """Candidates within this share of the cameras' distance from the axis of each other are one piece (3 cm on a
    40 cm orbit); the largest piece is the plant's body."""


def colour_histogram(rgb: np.ndarray, weights: np.ndarray, bins: int) -> np.ndarray:
    """A smoothed, normalised RGB histogram ``[bins, bins, bins]`` of colours ``rgb`` ``[N, 3]`` in [0, 1]."""
    idx = np.clip((rgb * bins).astype(int), 0, bins - 1)
    h = np.zeros((bins, bins, bins))
    np.add.at(h, (idx[:, 0], idx[:, 1], idx[:, 2]), weights)
    h = gaussian_filter(h, 1.0, mode="constant") + HISTOGRAM_FLOOR * max(h.sum(), 1.0) / bins ** 3
    return h / h.sum()


def colour_evidence(rgb: np.ndarray, plant_rgb: np.ndarray, plant_w: np.ndarray, room_rgb: np.ndarray,
                    room_w: np.ndarray, cfg: DecideConfig) -> np.ndarray:
    """Log-likelihood ratio (plant over the rest) of each colour of ``rgb`` ``[N, 3]`` under histograms of the sure
    plant and sure rest of the scene (weighted), clipped to ``cfg.max_colour_evidence``. ``[N]``"""
    hp = colour_histogram(plant_rgb, plant_w, cfg.colour_bins)
    hr = colour_histogram(room_rgb, room_w, cfg.colour_bins)
    idx = np.clip((rgb * cfg.colour_bins).astype(int), 0, cfg.colour_bins - 1)
    llr = np.log(hp[idx[:, 0], idx[:, 1], idx[:, 2]]) - np.log(hr[idx[:, 0], idx[:, 1], idx[:, 2]])
    return np.clip(llr, -cfg.max_colour_evidence, cfg.max_colour_evidence)


def neighbour_graph(mu: np.ndarray, rgb: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The k-nearest-neighbour graph of points ``mu`` ``[N, 3]``: ``(i [E], j [E], weight [E], typical distance)``.

    A weight falls with the colour difference (scaled by its mean, as GrabCut scales pixel differences)
    and with the distance beyond the typical (median) neighbour distance."""
    k = min(k, len(mu) - 1)
    d, nb = cKDTree(mu).query(mu, k=k + 1)
    i = np.repeat(np.arange(len(mu)), k)
    j = nb[:, 1:].reshape(-1)
    dist = d[:, 1:].reshape(-1)
    typical = float(np.median(dist)) if len(dist) else 1.0
    dc2 = ((rgb[i] - rgb[j]) ** 2).sum(1)
    w = np.exp(-dc2 / (2.0 * max(float(dc2.mean()), 1e-9))) * np.exp(-np.maximum(dist / max(typical, 1e-12) - 1.0, 0.0))
    return i, j, w, typical


def min_cut_labels(unary: np.ndarray, i: np.ndarray, j: np.ndarray, w: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    """Binary labels minimising ``sum(cost of each label) + sum over edges w (labels differ)``. ``[N]`` bool (True: the
    label ``unary > 0`` favours).

    ``unary`` ``[N]``: how much more the first label is favoured (log odds); edges ``i``, ``j`` with weights ``w``.
    Solved exactly as a minimum s-t cut (capacities scaled by ``scale`` and rounded to integers for
    scipy's maximum flow); the first label is the source side."""
    n = len(unary)
    s, t = n, n + 1
    cap_s = np.round(np.maximum(unary, 0.0) * scale).astype(np.int64)  # paid when a node leaves the source side
    cap_t = np.round(np.maximum(-unary, 0.0) * scale).astype(np.int64)
    cw = np.round(w * scale).astype(np.int64)
    rows = np.concatenate([np.full(n, s), np.arange(n), i, j])
    cols = np.concatenate([np.arange(n), np.full(n, t), j, i])
    caps = np.concatenate([cap_s, cap_t, cw, cw])
    graph = csr_matrix((caps, (rows, cols)), shape=(n + 2, n + 2))  # duplicate edges add up
    graph.sum_duplicates()
    graph.data = graph.data.astype(np.int32)
    flow = maximum_flow(graph, s, t).flow
    residual = (graph - flow).tocsr()
    residual.data[residual.data < 0] = 0
    residual.eliminate_zeros()
    reach = breadth_first_order(residual, s, directed=True, return_predecessors=False)
    side = np.zeros(n + 2, bool)
    side[reach] = True
    return side[:n]


def pieces(mu: np.ndarray, link: float) -> tuple[np.ndarray, float, np.ndarray]:
    """The pieces of the points ``mu`` ``[N, 3]`` and how far each lies from the plant's body: ``(gap [N], body size,
    piece label [N])``. Points within ``link`` of each other form a piece; the largest piece is the body (gap 0);
    another piece's gap is its shortest distance to the body. The body's size is the 95th percentile of its points'
    distances from their median."""
    pairs = cKDTree(mu).query_pairs(link, output_type="ndarray")
    graph = csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(mu), len(mu)))
    _, label = connected_components(graph, directed=False)
    body = label == np.argmax(np.bincount(label))
    size = float(np.percentile(np.linalg.norm(mu[body] - np.median(mu[body], axis=0), axis=1), BODY_SIZE_PERCENTILE))
    gap = piece_min(cKDTree(mu[body]).query(mu)[0], label)  # 0 on the body, whose points are their own nearest
    return gap, size, label


def piece_min(values: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Each point's piece's smallest value: ``values`` and piece ``label`` ``[N]``. ``[N]``"""
    smallest = np.full(label.max() + 1, np.inf)
    np.minimum.at(smallest, label, values)
    return smallest[label]


def support_reach(sfm_distance: np.ndarray, gap: np.ndarray) -> float:
    """How near an SfM point the body's Gaussians lie (the :data:`SUPPORT_PERCENTILE` percentile of their distances;
    ``sfm_distance`` and ``gap`` ``[N]`` over the candidates)."""
    return float(np.percentile(sfm_distance[gap == 0], SUPPORT_PERCENTILE))


def unsupported(sfm_distance: np.ndarray, gap: np.ndarray, label: np.ndarray,
                needs_support: np.ndarray | None = None) -> np.ndarray:
    """The candidates (``[N]`` bool) in pieces apart from the body none of whose Gaussians lies within
    :func:`support_reach` of an SfM point, and those of ``needs_support`` (``[N]`` bool, body included) that do not
    lie that near one themselves."""
    reach = support_reach(sfm_distance, gap)
    out = (gap > 0) & (piece_min(sfm_distance, label) > reach)
    if needs_support is not None:
        out |= needs_support & (sfm_distance > reach)
    return out


def colour_teachers(body: np.ndarray, sfm_distance: np.ndarray | None, reach: float) -> np.ndarray:
    """The Gaussians of the plant's ``body`` (indices) that teach its colours: those within ``reach`` of an SfM point
    (``sfm_distance`` ``[N]``), or the whole body where no distances are given or fewer than
    :data:`MIN_COLOUR_SAMPLES` are that near."""
    if sfm_distance is None or reach <= 0:
        return body
    near = body[sfm_distance[body] <= reach]
    return near if len(near) >= MIN_COLOUR_SAMPLES else body


def decide_plant(mu: np.ndarray, rgb: np.ndarray, weight: np.ndarray, candidate: np.ndarray,
                 rest: np.ndarray, orbit_radius: float, sfm_distance: np.ndarray | None = None,
                 cfg: DecideConfig | None = None, needs_support: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The plant among the ``candidate`` Gaussians (``[N]`` bool): ``(plant [N] bool, facts)``.

    ``mu`` ``[N, 3]`` centres; ``rgb`` ``[N, 3]`` base colours in [0, 1]; ``weight`` ``[N]`` how much each counts in
    the colour models (its opacity); ``rest``: Gaussians surely not plant (the far room, the floor, the pot, the
    cube); ``orbit_radius``: the cameras' distance from the axis (model units); ``sfm_distance`` ``[N]``: each
    Gaussian's distance to the nearest SfM point (None: none known). The plant's colours are learned from its body
    (:func:`pieces`) where SfM found it (:func:`colour_teachers`), the rest's from ``rest``. ``needs_support`` ``[N]``
    (bool): where a candidate needs an SfM point within the support reach even on the body (:func:`unsupported`; the
    pot's inside over the soil, where a quick model blurs the soil into layers joined to the crown)."""
    cfg = cfg or DecideConfig()
    idx = np.flatnonzero(candidate)
    plant = np.zeros(len(mu), bool)
    if len(idx) <= cfg.neighbours or not rest.any():
        plant[idx] = True
        return plant, {"decided_by": "position (too little to learn colours from)"}
    i, j, w, typical = neighbour_graph(mu[idx], rgb[idx], cfg.neighbours)
    gap, size, label = pieces(mu[idx], cfg.attach_reach * orbit_radius)
    body = idx[gap == 0]
    teach = colour_teachers(body, sfm_distance, cfg.teach_reach * typical)
    llr = colour_evidence(rgb[idx], rgb[teach], weight[teach], rgb[rest], weight[rest], cfg)
    held = np.ones(len(idx), bool) if sfm_distance is None else ~unsupported(
        sfm_distance[idx], gap, label, None if needs_support is None else needs_support[idx])
    prior = np.where(held, cfg.prior_log_odds, -cfg.prior_log_odds) - (gap / max(cfg.gap_scale * size, 1e-12)) ** 2
    keep = min_cut_labels(prior + llr, i, j, cfg.smoothness * w)
    plant[idx[keep]] = True
    facts = {"decided_by": "position, colour and neighbours", "candidates": int(len(idx)),
             "apart_from_body": int((gap > 0).sum()), "colours_from": int(len(teach)), "dropped": int((~keep).sum()),
             "dropped_apart": int((~keep & (gap > 0)).sum()), "unsupported": int((~held).sum()),
             "unsupported_on_body": int((~held & (gap == 0)).sum()),
             "neighbour_cm": round(typical, 3),
             "body_size": round(size, 2)}
    return plant, facts

"""One frame's mask from the capture's 3D object: the plant and cube as the model draws them, refined on the image.

:func:`object_prior` renders, for one camera, how much of each pixel is plant (the plant Gaussians' share of the
composite, so that whatever stands in front, such as the pot, hides it) and draws the calibrated cube exactly (its box
projected, less the pixels where a nearer Gaussian covers it). Cameras carry errors of a few pixels and the quick
model blurs thin parts, so :func:`refine` moves the outline onto the image's own edges: OpenCV's GrabCut, started from
the prior (sure inside, sure outside, undecided in a band along the outline, and the middle line of parts narrower
than the band sure inside), learns the frame's plant and background colours from the prior's labels and cuts once
along the strongest edges in the band (:data:`GRABCUT_ITERATIONS`). GrabCut's cut prefers short outlines and drops
parts a few pixels wide whatever their colour; in the prior's parts finer than the quick model can draw
(:func:`unresolved_px`) each pixel goes instead where its colour is likelier under GrabCut's two colour models. A
camera's pixels along an outline each see some plant and some room; the cut runs along the strongest edge and leaves
the pixels just outside it out, so each is put in when its colour says it is at least half plant
(:func:`add_mixed_outline`). The cube's silhouette is exact where the cut is not: its faces' light border meets a
light table with little contrast, and the cut takes it off, so :func:`object_mask` keeps the cube as drawn, whatever
the cut says.

Usage:
    plant, cube = object_prior(obj, view)
    mask = object_mask(rgb, plant, cube, band_px=6, thin_px=unresolved_px(rgb.shape, 360))
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from plantsplat.cube import cube_box_distance, in_cube_box
from plantsplat.segment.object3d import ObjectModel, camera_points, footprints, overlapping, render_values, union_box

SUBPIXEL_BITS = 4
"""The cube's silhouette is filled with its corners in fixed point with this many fractional bits (OpenCV's shift)."""
NEAR_REACH = 1.2
"""Gaussians nearer a camera than the object's axis less this many times its reach are floaters of the quick model."""
CUBE_SURFACE_CM = 0.5
"""Gaussians within this distance (cm) of the cube's box are the quick model's drawing of the cube's own faces: only
those farther out (the pot, a leaf), and this much nearer the camera than the face, hide the exact cube. Seen at a
slant, a face drawn a few millimetres off its plane lies a centimetre or more nearer than the face along the rays
(:func:`plantsplat.cube.cube_box_distance`)."""
GRABCUT_COMPONENTS = 5
"""Gaussians in each of GrabCut's colour models (OpenCV's fixed number)."""
GRABCUT_MODEL_SIZE = 13 * GRABCUT_COMPONENTS
"""Length of GrabCut's colour model arrays: per Gaussian a weight, a mean (3) and a covariance (9), in that order."""
GRABCUT_ITERATIONS = 1
"""GrabCut's rounds of learning its colour models and cutting. The first learns them from the prior's labels, which
multi-view geometry placed; each later one learns them from its own cut, so single-frame colour pulls the outline away
from the geometry: on the six foreign renders (2026-11-29) one round gave mean IoU 0.001-0.007 higher than three on
five of them (0.003 lower on 104), in half the time."""
MIXED_WINDOW_PX = 9
"""Side of the window in which the plant's and the room's colours next to an outline pixel are averaged."""
MIN_MIXED_CONTRAST = 20.0
"""Below this distance (0-255 levels, RGB) between those two colours a pixel's share of each cannot be told."""


def cube_depth(cube, view) -> tuple[np.ndarray, np.ndarray]:
    """The calibrated cube in a view: ``(silhouette [H, W] bool, depth of its nearest face [H, W], inf outside)``."""
    h = cube.size / 2
    corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (0.0, cube.size)])
    uv, z = camera_points(corners, view)
    sil = np.zeros((view.height, view.width), np.uint8)
    depth = np.full((view.height, view.width), np.inf)
    if (z <= 1e-6).any():
        return sil.astype(bool), depth
    hull = cv2.convexHull((uv - 0.5).astype(np.float32)).reshape(-1, 2)  # OpenCV draws pixel centres at integers
    cv2.fillConvexPoly(sil, np.round(hull * (1 << SUBPIXEL_BITS)).astype(np.int32), 1, shift=SUBPIXEL_BITS)
    ys, xs = np.nonzero(sil)
    # ray / box intersection (slab method) in the cube frame for the silhouette's pixels
    R, t = view.viewmat[:3, :3], view.viewmat[:3, 3]
    origin = -R.T @ t
    rays = np.linalg.solve(view.K, np.stack([xs + 0.5, ys + 0.5, np.ones(len(xs))]))  # [3, P] rays through pixel centres, z = 1
    d = (R.T @ rays).T  # [P, 3] world directions, scaled so that camera z = 1
    lo, hi = np.array([-h, -h, 0.0]), np.array([h, h, cube.size])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / d, (hi - origin) / d
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = far >= near
    depth[ys[hit], xs[hit]] = near[hit]  # the ray's parameter is the camera z (rays have z = 1)
    return np.isfinite(depth), depth


def object_prior(obj: ObjectModel, view) -> tuple[np.ndarray, np.ndarray]:
    """How much of each pixel of ``view`` is plant, and is cube, in [0, 1]: ``(plant, cube)``, ``[H, W]`` float32.

    Each is drawn with only the Gaussians whose footprint reaches its box (the plant Gaussians' footprints; the cube's
    silhouette), so most of the frame's room is not composited: outside the box nothing is plant or cube, and inside
    it the values are those of every Gaussian drawn (on 40 views of two captures the plant's bit for bit, the cube's
    within 1.2e-7 on a few pixels: the CPU kernels' rounding)."""
    p = obj.params
    n = len(obj.plant)
    mu = p["means"].numpy()
    plant = torch.zeros(n, 3)
    plant[torch.from_numpy(obj.plant)] = 1.0
    # nothing stands between the camera and the object (the filmer walks there): Gaussians nearer than the object's
    # region are floaters of the quick model, which can hang in front of one camera and veil the whole frame
    axis_depth = float(view.viewmat[2, :3] @ obj.axis + view.viewmat[2, 3])
    uv, z = camera_points(mu, view)
    keep = z > axis_depth - NEAR_REACH * obj.info["reach"]
    cube = np.zeros((view.height, view.width), np.float32)
    if obj.cube is not None:  # Gaussians of the cube give way to the exact cube
        keep &= ~in_cube_box(mu, obj.cube.size, 0.0)
    boxes = footprints(p, view)
    near_plant = keep & overlapping(boxes, union_box(boxes[keep & obj.plant]))
    img, _ = render_values(p, plant, view, keep=torch.from_numpy(near_plant))
    if obj.cube is not None:
        sil, depth = cube_depth(obj.cube, view)
        if sil.any():
            u = np.clip(np.floor(uv[:, 0]).astype(int), 0, view.width - 1)
            v = np.clip(np.floor(uv[:, 1]).astype(int), 0, view.height - 1)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < view.width) & (uv[:, 1] >= 0) & (uv[:, 1] < view.height)
            reference = np.where(inside & sil[v, u], depth[v, u], depth[sil].min())  # beside it: its nearest point
            ys, xs = np.nonzero(sil)
            # what stands before the cube: off its box (not its own faces) and above the ground (a segment from a
            # camera above the ground to the cube never dips below it; a Gaussian centred there draws the table)
            may_hide = (cube_box_distance(mu, obj.cube.size) > CUBE_SURFACE_CM) & (mu[:, 2] >= 0.0)
            front = (keep & (z < reference - CUBE_SURFACE_CM) & may_hide
                     & overlapping(boxes, np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])))
            _, cover = render_values(p, torch.ones(n, 3), view, keep=torch.from_numpy(front))  # Gaussians before it
            cube = (sil * (1.0 - cover)).astype(np.float32)
    return img[..., 0].astype(np.float32), cube


def distortion_map(view) -> tuple[np.ndarray, np.ndarray] | None:
    """Where each pixel of the (distorted) frame lies in the view's pinhole image: the two ``cv2.remap`` maps that
    bring a rendered prior onto the frame. None for a camera without distortion. ``view``: as
    :func:`plantsplat.train.data.load_scene` gives it (the frame's own lens in ``frame_dist``)."""
    dist = view.frame_dist
    if dist.size == 0 or not np.any(np.abs(dist) > 0):
        return None
    ys, xs = np.mgrid[0:view.height, 0:view.width].astype(np.float64)
    pts = cv2.undistortPoints(np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2), view.K, dist, P=view.K)
    pts = pts.reshape(view.height, view.width, 2).astype(np.float32)
    return pts[..., 0], pts[..., 1]


def cached_distortion_map(view, cache: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`distortion_map` of ``view``, made once per camera (intrinsics, lens and size) and kept in ``cache``: an
    imported model may give each frame a camera of its own."""
    key = (np.asarray(view.K, np.float64).tobytes(), np.asarray(view.frame_dist, np.float64).tobytes(),
           view.width, view.height)
    if key not in cache:
        cache[key] = distortion_map(view)
    return cache[key]


def to_frame(prior: np.ndarray, maps: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """A prior rendered through the pinhole camera, moved onto the distorted frame (see :func:`distortion_map`)."""
    if maps is None:
        return prior
    return cv2.remap(prior, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def unresolved_px(frame_shape: tuple, scene_resolution: int) -> int:
    """Width (frame pixels, odd) below which a part's outline is finer than the quick model, trained with
    ``scene_resolution`` px on the frames' longest side, can draw: two of its pixels, rounded up."""
    return 2 * math.ceil(max(frame_shape[:2]) / scene_resolution) + 1


def narrow_parts(mask: np.ndarray, width_px: int) -> np.ndarray:
    """The parts of ``mask`` (``[H, W]`` uint8 0/1) narrower than ``width_px``: those an opening by a disc that wide
    removes. ``[H, W]`` bool"""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (width_px, width_px))
    return (mask > 0) & ~(cv2.dilate(cv2.erode(mask, disc), disc) > 0)


def thin_ridge(mask: np.ndarray, disc: np.ndarray) -> np.ndarray:
    """The middle line of the thin parts of ``mask`` (``[H, W]`` uint8 0/1): the parts an opening by ``disc`` removes
    (narrower than it: petioles, stalks, stolons), at their local maxima of the distance to the outline, at least a
    pixel in. ``[H, W]`` bool

    Refining a prior, GrabCut keeps only what it learned as plant colour in a band along the outline, and a part
    narrower than the band has no sure core: on the foreign renders it cut most thin petioles out of the masks (a
    third of their pixels kept), and a flower on a thin stalk out of half the frames, which training then lost.
    """
    thin = narrow_parts(mask, disc.shape[0])
    dist = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
    ridge = dist >= cv2.dilate(dist, np.ones((3, 3), np.uint8))  # [H, W]: no neighbour farther from the outline
    return thin & ridge & (dist >= 1.0)


def object_mask(rgb: np.ndarray, plant: np.ndarray, cube: np.ndarray, band_px: int = 6, thin_px: int = 0,
                seed: int = 0) -> np.ndarray:
    """A frame's mask ``[H, W]`` bool from its prior (:func:`object_prior`): the outline of plant and cube together
    refined on the image (:func:`refine`; ``band_px`` 0: not refined), and every pixel the cube covers (``cube > 0.5``)
    kept. The cube is drawn from its calibrated pose and known size, within a pixel of the true silhouette on most
    frames; the cut leaves off its faces' light border where they meet a light table (0.9-1.6 % of the true and found
    masks' union on five of the six foreign renders, 2026-11-29)."""
    prior = np.maximum(plant, cube)
    mask = prior > 0.5 if band_px <= 0 else refine(rgb, prior, band_px, thin_px, seed=seed)
    return mask | (cube > 0.5)


def refine(rgb: np.ndarray, prior: np.ndarray, band_px: int = 6, thin_px: int = 0, iterations: int = GRABCUT_ITERATIONS,
           margin_px: int = 24, seed: int = 0) -> np.ndarray:
    """The mask ``[H, W]`` bool: ``prior > 0.5`` with its outline moved onto the image's edges by GrabCut within
    ``band_px`` of it (in the prior's bounding box grown by ``margin_px``, where all the work is); the middle line of
    the prior's parts narrower than the band stays plant (:func:`thin_ridge`). In its parts narrower than ``thin_px``
    (odd; 0: none), whose outline the prior cannot place, and in the pixels touching them, a pixel the cut left out is
    plant when its colour is likelier under GrabCut's plant model than under its background model: the cut's
    preference for short outlines drops thin petioles and stalks, one to three pixels wide, whatever their colour.
    The same preference fills the prior's gaps narrower than the band (the room seen between petioles, which the cut
    reaches from both sides), so there a pixel the cut put in stays plant only when its colour is likelier plant.
    Last, the pixels touching the cut from outside that are at least half plant are put in (:func:`add_mixed_outline`).
    ``seed``: of GrabCut's k-means, so that a frame's mask does not depend on the frames refined before it on the same
    thread."""
    fg = prior > 0.5
    if not fg.any():
        return fg
    ys, xs = np.nonzero(fg)
    H, W = fg.shape
    y0, y1 = max(0, ys.min() - margin_px), min(H, ys.max() + margin_px + 1)
    x0, x1 = max(0, xs.min() - margin_px), min(W, xs.max() + margin_px + 1)
    crop = fg[y0:y1, x0:x1].astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
    grown, shrunk = cv2.dilate(crop, k) > 0, cv2.erode(crop, k) > 0
    m = np.full(crop.shape, cv2.GC_BGD, np.uint8)
    m[grown] = cv2.GC_PR_BGD
    m[crop > 0] = cv2.GC_PR_FGD
    m[shrunk] = cv2.GC_FGD
    m[thin_ridge(crop, k)] = cv2.GC_FGD  # a petiole the 3D decision found stays, however GrabCut's colours lean
    cut = (m == cv2.GC_FGD) | (m == cv2.GC_PR_FGD)
    if (m == cv2.GC_FGD).any() and (m == cv2.GC_BGD).any():
        bgd, fgd = np.zeros((1, GRABCUT_MODEL_SIZE)), np.zeros((1, GRABCUT_MODEL_SIZE))
        bgr = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
        cv2.setRNGSeed(seed)  # GrabCut's k-means draws from this thread's generator: the same mask on any thread
        cv2.grabCut(bgr, m, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
        cut = (m == cv2.GC_FGD) | (m == cv2.GC_PR_FGD)
        if thin_px > 1:  # the narrow parts and the pixels touching them: their true edge may lie a pixel beyond
            near = cv2.dilate(narrow_parts(crop, thin_px).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            left_out = near & ~cut
            cut[left_out] = likelier_plant(bgr[left_out], fgd, bgd)
        put_in = cut & (cv2.erode(grown.astype(np.uint8), k) > 0) & (crop == 0)  # in the prior's narrow gaps
        cut[put_in] = likelier_plant(bgr[put_in], fgd, bgd)
        cut = add_mixed_outline(bgr, cut)
    out = np.zeros_like(fg)
    out[y0:y1, x0:x1] = cut
    return out


def add_mixed_outline(image: np.ndarray, mask: np.ndarray, window_px: int = MIXED_WINDOW_PX,
                      min_contrast: float = MIN_MIXED_CONTRAST) -> np.ndarray:
    """``mask`` (``[H, W]`` bool) with each pixel touching it from outside added when at least half of it is plant.

    A pixel on an outline mixes the colours of what lies either side of it. Its share of plant is read off the line
    between the plant's colour next to it (the mask's pixels in a ``window_px`` window) and the room's (the pixels in
    the window neither in the mask nor touching it): where its colour lies past the middle of that line, towards the
    plant, it is plant. Where the two colours are nearer than ``min_contrast`` the pixel stays out. ``image``:
    ``[H, W, 3]`` uint8, in any channel order."""
    m8 = mask.astype(np.uint8)
    ring = (cv2.dilate(m8, np.ones((3, 3), np.uint8)) > 0) & ~mask
    if not ring.any():
        return mask
    colour = image.astype(np.float32)
    plant, n_plant = _window_mean(colour, mask, window_px)
    room, n_room = _window_mean(colour, ~(ring | mask), window_px)
    line = plant - room
    length2 = (line * line).sum(-1)
    share = ((colour - room) * line).sum(-1) / np.maximum(length2, 1e-6)
    add = ring & (n_plant > 0) & (n_room > 0) & (length2 > min_contrast ** 2) & (share >= 0.5)
    return mask | add


def _window_mean(colour: np.ndarray, where: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean of ``colour`` ``[H, W, 3]`` over the pixels ``where`` in the ``window_px`` window around each pixel,
    and how many there are: ``([H, W, 3], [H, W])``."""
    w = where.astype(np.float32)
    n = cv2.boxFilter(w, -1, (window_px, window_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(colour * w[..., None], -1, (window_px, window_px), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    return total / np.maximum(n, 1e-6)[..., None], n


def likelier_plant(colours: np.ndarray, plant_model: np.ndarray, background_model: np.ndarray) -> np.ndarray:
    """Whether each of ``colours`` ``[N, 3]`` is likelier under GrabCut's plant colour model than under its
    background model (:func:`colour_log_likelihood`). ``[N]`` bool"""
    if not len(colours):
        return np.zeros(0, bool)
    x = colours.astype(np.float64)
    return colour_log_likelihood(plant_model, x) > colour_log_likelihood(background_model, x)


def colour_log_likelihood(model: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Log-likelihood of ``colours`` ``[N, 3]`` (in the image's channel order) under one of GrabCut's colour models
    (``[1, GRABCUT_MODEL_SIZE]`` as ``cv2.grabCut`` fills it). ``[N]``"""
    k = GRABCUT_COMPONENTS
    flat = model.reshape(-1)
    weights, means, covs = flat[:k], flat[k:4 * k].reshape(k, 3), flat[4 * k:13 * k].reshape(k, 3, 3)
    used = np.flatnonzero(weights > 0)
    logs = [np.log(weights[j]) + multivariate_normal(means[j], covs[j], allow_singular=True).logpdf(colours)
            for j in used]
    return logsumexp(np.stack(logs).reshape(len(used), -1), axis=0) if len(used) else np.full(len(colours), -np.inf)

"""What is object in 3D: the plant's Gaussians in a quick whole-scene model, and the calibrated cube.

The poses stage gives every frame a camera in the cube frame (cm, z up, the cube's bottom face on
the ground at the origin). What holds in any room:

- the cube is a known 10 cm box standing at the origin;
- the plant stands where the cameras look: on the vertical axis through the point closest to every
  optical axis (:func:`orbit_axis`), above the ground;
- the pot and its soil are a thick solid around that axis on the ground; leaves, petioles and fruit
  are thin. Space the cameras see through is free; a solid is never seen through. Free space is
  carved from the model's depth in every view (:func:`carve`); what survives an erosion by a few
  centimetres near the axis is the pot (:func:`pot_solid`);
- the room is far: the plant is in view in (nearly) every frame, while a Gaussian that stands in for
  a blank ceiling or wall at the wrong depth near the axis leaves the frame in many of them
  (:func:`in_view_share`); a leaf tip of a plant wider than the frames leaves some of them too, and
  stays plant when it joins the plant's body (:func:`join_out_of_frame`).

:func:`object_model` puts these together into an :class:`ObjectModel`: which Gaussians of the scene
model are plant, and the cube. Without a calibrated cube there is no ground, pot or cube: the plant
is what stands near the orbit's axis, in view of the cameras.

Usage:
    obj = object_model(params, views, calibrated=True)
    int(obj.plant.sum()), obj.pot
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from plantsplat.cube import CubeSpec, in_cube_box
from plantsplat.log import get_logger
from plantsplat.poses.checks import orbit_centre
from plantsplat.raster import rasterize
from plantsplat.raster.cpu_projection import project_cpu
from plantsplat.raster.projection import quat_scale_to_covar
from plantsplat.segment.decide import DecideConfig, decide_plant
from plantsplat.segment.soil import soil_layer
from plantsplat.train.model import sh_to_rgb

log = get_logger(__name__)


@dataclass
class ObjectModel:
    """The capture's object: the scene model's Gaussians with a plant flag, the cube and the geometry found."""

    params: dict  # name -> tensor, activated on use (means [N, 3], quats [N, 4], scales [N, 3] log, opacities [N] logit)
    plant: np.ndarray  # [N] bool: Gaussians of the plant
    cube: CubeSpec | None  # the calibration cube at the origin (None: no calibrated cube)
    axis: np.ndarray  # [2] xy of the vertical axis the cameras circle (or [3] point + up in the model frame)
    up: np.ndarray  # [3] the world's up
    info: dict = field(default_factory=dict)
    part: np.ndarray | None = None  # [N] int8: what each Gaussian was decided to be (:data:`PART_NAMES`)


PART_NAMES = ("room", "plant", "pot", "cube", "set aside")
"""What :func:`object_model` calls each Gaussian (``ObjectModel.part`` indexes this): the room; the plant; the pot and
its soil; the calibration cube; a candidate in the plant's region that the evidence set aside (not plant)."""


def orbit_axis(c2ws: list[np.ndarray]) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis: what the cameras circle. ``[3]``"""
    c = orbit_centre(c2ws)
    if c is None:
        return np.mean([M[:3, 3] for M in c2ws], axis=0)
    return c


def up_from_orbit(c2ws: list[np.ndarray], centre: np.ndarray) -> np.ndarray:
    """Without a calibrated cube: the normal of the plane the cameras move in, turned towards the cameras'
    side of the object (cameras look at a plant from around and above it). ``[3]``"""
    C = np.array([M[:3, 3] for M in c2ws])
    n = np.linalg.svd(C - C.mean(0))[2][-1]
    return n if n @ (C.mean(0) - centre) >= 0 else -n


def camera_points(points: np.ndarray, view) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[N, 2]`` and depth ``[N]`` of world points in a pinhole view (``train.data.View``).

    Coordinates as the rasterizer and COLMAP count them: pixel ``(i, j)`` spans ``[i, i + 1) x [j, j + 1)``.
    """
    Xc = points @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]
    z = Xc[:, 2]
    uv = Xc @ view.K.T
    return uv[:, :2] / np.maximum(uv[:, 2:], 1e-9), z


def in_view_share(points: np.ndarray, views: list) -> np.ndarray:
    """Share of the views whose frame holds each point (in front of the camera, inside the image). ``[N]``"""
    n = np.zeros(len(points))
    for v in views:
        uv, z = camera_points(points, v)
        n += (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < v.width) & (uv[:, 1] >= 0) & (uv[:, 1] < v.height)
    return n / max(len(views), 1)


def _scaled_K(view, scale: float) -> torch.Tensor:
    """The view's intrinsics for an image ``scale`` times its size (pixel edges at integers: all of K scales)."""
    K = torch.tensor(view.K, dtype=torch.float32).clone()
    K[:2] *= scale
    return K


def render_values(params: dict, values: torch.Tensor, view, scale: float = 1.0, keep: torch.Tensor | None = None):
    """Composite per-Gaussian ``values`` ``[N, 3]`` into a view (``scale`` times its size): ``(image [h, w, 3], alpha
    [h, w])`` as numpy. ``keep`` [N] bool draws only some Gaussians."""
    mu, q, s, o = params["means"], params["quats"], params["scales"], params["opacities"]
    if keep is not None:
        mu, q, s, o, values = mu[keep], q[keep], s[keep], o[keep], values[keep]
    w, h = int(round(view.width * scale)), int(round(view.height * scale))
    with torch.no_grad():
        out = rasterize(mu, q, torch.exp(s), torch.sigmoid(o).reshape(-1), values,
                        torch.tensor(view.viewmat, dtype=torch.float32), _scaled_K(view, scale), w, h, backend="cpu")
    return out.color.numpy(), out.alpha.reshape(h, w).numpy()


FOOTPRINT_MARGIN_PX = 2
"""Pixels each Gaussian's footprint (:func:`footprints`) is grown by, a margin for the rounding of its box."""


def footprints(params: dict, view) -> np.ndarray:
    """Each Gaussian's footprint in a view: the pixel box ``[x0, y0, x1, y1)`` (grown by :data:`FOOTPRINT_MARGIN_PX`)
    outside which it is fainter than the rasterizer draws (alpha < 1/255); empty (``x1 <= x0``) for a Gaussian not
    drawn in the view. ``[N, 4]`` int64"""
    with torch.no_grad():  # the rasterizer's own projection (numba)
        m2d, _, _, radii = project_cpu(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]).reshape(-1),
            torch.tensor(view.viewmat, dtype=torch.float32), _scaled_K(view, 1.0), view.width, view.height)
    m, r = m2d.double().numpy(), radii.numpy().astype(np.int64)
    lo = np.floor(m - r - FOOTPRINT_MARGIN_PX).astype(np.int64)
    hi = np.ceil(m + r + FOOTPRINT_MARGIN_PX).astype(np.int64) + 1
    box = np.concatenate([lo, hi], axis=1)
    box[(r <= 0).all(axis=1)] = 0  # not drawn: an empty box
    return box


def union_box(boxes: np.ndarray) -> np.ndarray:
    """The box ``[x0, y0, x1, y1)`` around the non-empty ``boxes`` ``[N, 4]`` (empty when none is)."""
    full = boxes[(boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])]
    if not len(full):
        return np.zeros(4, np.int64)
    return np.concatenate([full[:, :2].min(axis=0), full[:, 2:].max(axis=0)])


def overlapping(boxes: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Which ``boxes`` ``[N, 4]`` share a pixel with ``box``. ``[N]`` bool"""
    return ((boxes[:, 0] < box[2]) & (boxes[:, 2] > box[0]) & (boxes[:, 1] < box[3]) & (boxes[:, 3] > box[1])
            & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1]))


def horizontal_spread(params: dict) -> np.ndarray:
    """Each Gaussian's covariance in the ground plane (the x-y block of its 3D covariance): ``[N, 2, 2]``."""
    with torch.no_grad():
        cov = quat_scale_to_covar(params["quats"], torch.exp(params["scales"]))  # [N, 3, 3]
    return cov[:, :2, :2].numpy().astype(np.float64)


def depth_map(params: dict, view, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Expected depth of the model's surface (camera z, model units) and its alpha, at ``scale``. ``[h, w]`` each."""
    mu = params["means"].numpy()
    z = mu @ view.viewmat[2, :3] + view.viewmat[2, 3]
    img, alpha = render_values(params, torch.tensor(np.repeat(z[:, None], 3, 1), dtype=torch.float32), view, scale)
    return img[..., 0] / np.maximum(alpha, 1e-6), alpha


@dataclass
class Pot:
    """A pot found as rings of Gaussians around the axis: its axis ``centre`` ``[2]``, rim and soil heights and the
    radius at each height (``heights`` and ``radii`` from the ground up to the rim)."""

    centre: np.ndarray
    rim_z: float
    soil_z: float
    heights: np.ndarray
    radii: np.ndarray
    soil_bottom: float
    """The lowest slab of the band of slabs, from :attr:`soil_z` down, that cover the pot's inside (:attr:`soil_z`
    itself for one slab, or where the soil was not seen): a soil seen at grazing angles is drawn as a layer some slabs
    thick, and the soil's surface lies within it."""
    wall: float = 1.5
    """How far inside the outer radius the pot's wall and rim reach (cm); above the soil, inside that, is plant."""
    soil_points: int = 0
    """How many SfM points lie in the soil's layer when :attr:`soil_z` is theirs (:func:`with_sfm_soil`); 0 when it is
    the quick model's."""
    soil_thickness: float = 0.0
    """The RMS distance of those SfM points from :attr:`soil_z` (cm): how thick the soil's surface is (about a
    millimetre on the benchmark captures); 0 for the quick model's soil."""

    @property
    def soil_seen(self) -> bool:
        """Whether the soil was seen below the rim (else :attr:`soil_z` is the rim, only its upper bound)."""
        return self.soil_z < self.rim_z

    def contains(self, points: np.ndarray, margin: float) -> np.ndarray:
        """Points ``[N, 3]`` of the pot (its body up to the soil, its wall up to the rim), grown by ``margin``. ``[N]``

        Where the soil was not seen, only the wall is known to be pot: the inside below the rim may hold the crown
        and the petioles' feet (the leaves hid them with the soil), and is left to the other evidence. Where SfM
        points put the soil, the body's margin above it is narrower in the crown's disc (:meth:`soil_margin`)."""
        z = points[:, 2]
        r = np.interp(z, self.heights, self.radii)
        d = np.linalg.norm(points[:, :2] - self.centre, axis=1)
        body = z <= self.soil_z + self.soil_margin(d, margin) if self.soil_seen else np.zeros(len(z), bool)
        wall = (d > r - self.wall) & (z < self.rim_z + margin)
        return (d < r + margin) & (z > -margin) & (body | wall)

    def soil_margin(self, d: np.ndarray, margin: float) -> np.ndarray:
        """How far above the soil the pot's body reaches at distances ``d`` ``[N]`` from its axis (cm). ``margin``
        for the quick model's own soil, drawn a centimetre or more thick. Where SfM points put the soil
        (:func:`with_sfm_soil`), ``margin`` still over the outer part of the inside, where the soil heaps against the
        wall and the quick model draws it above the points' layer, but only the layer's own thickness
        (:attr:`soil_thickness`) within :data:`CROWN_SHARE` of the inside's radius, where the crown and the petioles'
        feet stand on the soil: what lies there above it is left to the evidence. ``[N]``"""
        if not self.soil_points:
            return np.full(len(d), float(margin))
        crown = d < CROWN_SHARE * pot_inside_radius(self.radii[-1])
        return np.where(crown, min(self.soil_thickness, float(margin)), float(margin))

    def over_soil(self, points: np.ndarray) -> np.ndarray:
        """Points ``[N, 3]`` in the pot's inside between the soil SfM points put (:func:`with_sfm_soil`) and the rim,
        where a quick model blurs the soil into half-transparent layers over it; none where the soil is the quick
        model's own or was not seen. ``[N]``"""
        if not self.soil_points:
            return np.zeros(len(points), bool)
        d = np.linalg.norm(points[:, :2] - self.centre, axis=1)
        z = points[:, 2]
        return (d < pot_inside_radius(self.radii[-1])) & (z > self.soil_z) & (z < self.rim_z)

    def summary(self) -> dict:
        return {"centre_cm": np.round(self.centre, 2).tolist(), "rim_z_cm": round(self.rim_z, 2),
                "soil_z_cm": round(self.soil_z, 2), "soil_bottom_z_cm": round(self.soil_bottom, 2),
                "soil_sfm_points": self.soil_points, "soil_thickness_cm": round(self.soil_thickness, 3),
                "rim_radius_cm": round(float(self.radii[-1]), 2), "base_radius_cm": round(float(self.radii[0]), 2)}


def _circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle through 2D points ``[N, 2]``: ``(centre [2], radius)``."""
    A = np.c_[2 * xy, np.ones(len(xy))]
    c = np.linalg.lstsq(A, (xy ** 2).sum(1), rcond=None)[0]
    return c[:2], float(np.sqrt(max(c[2] + c[0] ** 2 + c[1] ** 2, 0.0)))


def ring(xy: np.ndarray, axis_xy: np.ndarray, rng: np.random.Generator, band: float = 0.5, sectors: int = 16,
         trials: int = 300, r_range: tuple[float, float] = (3.0, 16.0), max_offset: float = 5.0, contrast: float = 3.0,
         min_points: int = 10):
    """The best horizontal ring in a slab of points ``xy [N, 2]`` (RANSAC circles near the axis): ``(sectors of the
    circle covered, inliers, centre, radius)`` or None. A pot's wall and rim are thin shells seen all around:
    the band of ``band`` cm on either side of the circle holds ``contrast`` times as many points per width as the
    annulus beside it. Leaves at one height lie at many radii: no such shell. A slab of fewer than ``min_points``
    points holds none."""
    if len(xy) < min_points:
        return None
    best = None
    dist = np.linalg.norm(xy - axis_xy, axis=1)
    outer = np.flatnonzero(dist >= np.median(dist))  # a wall is outside what it holds (soil, crown)
    for k in range(trials):
        pool = outer if k % 2 and len(outer) >= 3 else np.arange(len(xy))
        c, r = _circle(xy[rng.choice(pool, 3, replace=False)])
        if not r_range[0] <= r <= r_range[1] or np.linalg.norm(c - axis_xy) > max_offset:
            continue
        inl = np.abs(np.linalg.norm(xy - c, axis=1) - r) < band
        az = np.arctan2(xy[inl, 1] - c[1], xy[inl, 0] - c[0])
        cov = len(np.unique(np.floor((az + np.pi) / (2 * np.pi) * sectors).astype(int) % sectors))
        if best is None or (cov, int(inl.sum())) > best[:2]:
            best = (cov, int(inl.sum()), c, r)
    if best is None:
        return None
    d = np.abs(np.linalg.norm(xy - best[2], axis=1) - best[3])
    beside = int(((d >= band) & (d < 4 * band)).sum())  # the annulus around the band, three times as wide
    if best[1] < contrast * beside / 3:
        return None  # points spread over many radii (foliage) make circles too, but not a thin shell
    c, r = _circle(xy[d < band])
    return best[0], best[1], c, r


TOP_PERCENTILE = 99.9
"""The decided plant's top is this percentile of its opaque Gaussians' heights."""
TOP_OPACITY = 0.5
"""Gaussians at least this opaque count for the decided plant's top."""
POT_SLAB_CM = 0.5
"""Thickness of the horizontal slabs the pot (and its soil) is looked for in: the soil's height is known to it."""
POT_INSIDE_SHARE = 0.8
"""The pot's inside, where its soil is looked for: this share of the rim's radius (within the wall and the rim's lip)."""
SOIL_DEPTH_CM = 6.0
"""How far below the rim the soil is looked for (cm)."""
CROWN_SHARE = 0.5
"""The crown's disc: this share of the pot's inside radius around its axis (a quarter of the inside's area), where
what stands on a soil SfM points put is left to the evidence (:meth:`Pot.soil_margin`)."""
FOOTPRINT_FLOOR_CM2 = 1e-6
"""Added to a footprint's covariance (cm²) so that a needle-thin Gaussian's can be inverted."""


def find_pot(points: np.ndarray, axis_xy: np.ndarray, slab: float = POT_SLAB_CM, reach: float = 16.0,
             min_sectors: int = 14, seed: int = 0, window: float = 1.5, wall_offset_cm: float = 1.5,
             spread: np.ndarray | None = None) -> Pot | None:
    """The pot standing on the ground around the axis, from the model's Gaussians ``points [N, 3]`` (cube frame).

    Each horizontal slab (``slab`` cm, from the ground up; its points within ``window`` slabs of its height) is
    searched for a ring around the axis (:func:`ring`); the rim is the strongest ring seen all around (at least
    ``min_sectors`` of 16 directions), its top the highest slab above it that still holds that ring. The wall below follows
    the rings found there whose centre lies within ``wall_offset_cm`` of the rim's (a pot widens or narrows
    evenly). None when no ring is strong enough. ``spread`` ``[N, 2, 2]``: each point's horizontal covariance (a
    Gaussian's footprint, for the soil's cover: :func:`soil_band_in_pot`); None for points without extent.
    """
    rng = np.random.default_rng(seed)
    close = np.linalg.norm(points[:, :2] - axis_xy, axis=1) < reach
    near = points[close]
    rings = []
    for z in np.arange(slab, near[:, 2].max(initial=0.0), slab):
        found = ring(near[np.abs(near[:, 2] - z) < window * slab][:, :2], axis_xy, rng)
        if found is not None and found[0] >= min_sectors:
            rings.append((float(z), *found))
    if not rings:
        return None
    k = max(range(len(rings)), key=lambda i: rings[i][2])
    z_rim, _, _, centre, r_rim = rings[k]
    for z, _, _, c, r in rings[k + 1:]:  # the rim's top: the same ring a little higher
        if z - z_rim > 3 * slab or abs(r - r_rim) > 1.0 or np.linalg.norm(c - centre) > 1.0:
            break
        z_rim = z
    wall = [(z, r) for z, _, _, c, r in rings
            if z < z_rim and np.linalg.norm(c - centre) < wall_offset_cm and r <= r_rim + 1.0]
    heights = np.array([0.0] + [z for z, _ in wall] + [z_rim])
    radii = np.array([wall[0][1] if wall else r_rim] + [r for _, r in wall] + [r_rim])
    top, bottom = soil_band_in_pot(near, centre, r_rim, z_rim, slab, spread=None if spread is None else spread[close])
    return Pot(centre=np.asarray(centre), rim_z=float(z_rim), soil_z=top, heights=heights,
               radii=np.maximum.accumulate(radii), soil_bottom=bottom)


def pot_inside_radius(rim_radius: float) -> float:
    """The radius of a pot's inside (cm), where its soil is looked for: :data:`POT_INSIDE_SHARE` of its rim's."""
    return POT_INSIDE_SHARE * float(rim_radius)


def pot_soil_layer(sfm_points: np.ndarray, centre, rim_radius: float, rim_z: float):
    """The layer of SfM points on the soil of a pot (rim of ``rim_radius`` at ``rim_z`` around ``centre``), looked for in
    its inner disc down to :data:`SOIL_DEPTH_CM` below the rim in :data:`POT_SLAB_CM` slabs
    (:func:`plantsplat.segment.soil.soil_layer`); None where there is none."""
    return soil_layer(sfm_points, np.asarray(centre, float), pot_inside_radius(rim_radius), float(rim_z),
                      slab=POT_SLAB_CM, depth=SOIL_DEPTH_CM)


def with_sfm_soil(pot: Pot, sfm_points: np.ndarray) -> Pot:
    """``pot`` with its soil at the layer of SfM points inside it (:func:`pot_soil_layer`), where
    there is one; else ``pot`` as found in the quick model.

    Structure from motion puts textured soil at the depth the frames agree on; the quick model, fitted at a third of
    the frames' resolution, can draw it as a layer a centimetre or two thick, or at every depth down to the pot's
    bottom (a dark soil in a black pot), where its slabs cover the inside nowhere and the soil counts as not seen."""
    if not len(sfm_points):
        return pot
    layer = pot_soil_layer(sfm_points, pot.centre, pot.radii[-1], pot.rim_z)
    if layer is None:
        return pot
    return replace(pot, soil_z=layer.z, soil_bottom=layer.z, soil_points=layer.points, soil_thickness=layer.thickness)


def soil_band_in_pot(points: np.ndarray, centre: np.ndarray, r_rim: float, z_rim: float, slab: float,
                     depth: float = SOIL_DEPTH_CM, cover: float = 0.5, rings: int = 8,
                     sectors: int = 16,
                     spread: np.ndarray | None = None) -> tuple[float, float]:
    """The soil in a pot as the band of slabs that cover its inside: ``(top, bottom)``. The top is the highest slab
    below the rim whose Gaussians cover at least ``cover`` of the pot's inside (:func:`pot_inside_radius`, in
    ``rings`` rings of equal area x ``sectors`` directions), the bottom the lowest of the slabs below it that still
    do, without a gap; ``(rim, rim)`` when none does. The crown and the petioles' feet above the soil are near the
    axis and do not cover the disc. A cell is covered when a point of the slab lies in it or, with ``spread``
    (``[N, 2, 2]`` horizontal covariances), when its centre lies within one standard deviation of a point's
    footprint: a quick model draws an even soil with a few wide, flat Gaussians, whose centres alone leave most
    cells empty."""
    rin = pot_inside_radius(r_rim)
    d = np.linalg.norm(points[:, :2] - centre, axis=1)
    az = np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0])
    cell_xy = _disc_cells(centre, rin, rings, sectors)  # [rings * sectors, 2]
    band: list[float] = []
    for z in np.arange(z_rim, z_rim - depth, -slab):
        s = np.abs(points[:, 2] - z) < slab
        inside = s & (d < rin)
        cells = np.zeros((rings, sectors), bool)
        cells[np.minimum((d[inside] / rin) ** 2 * rings, rings - 1).astype(int),
              np.floor((az[inside] + np.pi) / (2 * np.pi) * sectors).astype(int) % sectors] = True
        if spread is not None and s.any():
            cells |= _within_footprints(cell_xy, points[s, :2], spread[s]).reshape(rings, sectors)
        if cells.mean() >= cover:
            band.append(float(z))
        elif band:
            break
    return (band[0], band[-1]) if band else (float(z_rim), float(z_rim))


def _disc_cells(centre: np.ndarray, radius: float, rings: int, sectors: int) -> np.ndarray:
    """Centres ``[rings * sectors, 2]`` of a disc's cells (rings of equal area x sectors, row-major by ring), in the
    order :func:`soil_band_in_pot` indexes them."""
    r = radius * np.sqrt((np.arange(rings) + 0.5) / rings)
    a = (np.arange(sectors) + 0.5) / sectors * 2 * np.pi - np.pi
    return centre + np.stack([np.outer(r, np.cos(a)), np.outer(r, np.sin(a))], -1).reshape(-1, 2)


def _within_footprints(xy: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Whether each point ``xy`` ``[C, 2]`` lies within one standard deviation of any footprint (centres ``mu``
    ``[G, 2]``, covariances ``cov`` ``[G, 2, 2]``). ``[C]`` bool"""
    inv = np.linalg.inv(cov + FOOTPRINT_FLOOR_CM2 * np.eye(2))  # [G, 2, 2]
    d = xy[:, None, :] - mu[None, :, :]  # [C, G, 2]
    return (np.einsum("cgi,gij,cgj->cg", d, inv, d) <= 1.0).any(axis=1)


@dataclass
class Grid:
    """A box of cubic voxels: ``origin`` (the first voxel's corner, ``[3]``), ``step`` (edge length), ``shape``."""

    origin: np.ndarray
    step: float
    shape: tuple[int, int, int]

    def centres(self) -> np.ndarray:
        """Voxel centres ``[X*Y*Z, 3]`` in C order of :attr:`shape`."""
        axes = [self.origin[k] + (np.arange(self.shape[k]) + 0.5) * self.step for k in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel indices ``[N, 3]`` of points and whether each lies inside the grid ``[N]``."""
        ijk = np.floor((points - self.origin) / self.step).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.array(self.shape)), axis=1)
        return np.clip(ijk, 0, np.array(self.shape) - 1), inside


def carve(grid: Grid, views: list, depths: list[tuple[np.ndarray, np.ndarray]], scale: float, margin: float):
    """Per voxel: in how many views it lies in front of the model's surface (free space), and in how many
    views' frames it lies. ``(free [X, Y, Z], seen [X, Y, Z])`` counts. ``depths``: :func:`depth_map` of each view."""
    pts = grid.centres()
    free = np.zeros(len(pts), np.int32)
    seen = np.zeros(len(pts), np.int32)
    for v, (d, a) in zip(views, depths):
        uv, z = camera_points(pts, v)
        u, w_ = np.floor(uv[:, 0] * scale).astype(np.int64), np.floor(uv[:, 1] * scale).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (u < d.shape[1]) & (w_ >= 0) & (w_ < d.shape[0])
        seen += ok
        k = np.flatnonzero(ok)
        free[k] += (a[w_[k], u[k]] > 0.5) & (z[k] < d[w_[k], u[k]] - margin)
    return free.reshape(grid.shape), seen.reshape(grid.shape)


def _ball(radius_voxels: int) -> np.ndarray:
    r = int(radius_voxels)
    x, y, z = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    return x * x + y * y + z * z <= r * r + 1e-9


def pot_solid(grid: Grid, free: np.ndarray, seen: np.ndarray, axis_xy: np.ndarray, cube: CubeSpec | None,
              thickness: float, near_axis: float, min_seen: int) -> np.ndarray:
    """The thick solid standing around the axis (pot and soil): voxels no view sees through, opened by a ball of
    ``thickness`` (leaves, petioles and fruit are thinner and vanish), the pieces within ``near_axis`` of the
    axis, grown back by the ball and one voxel (their surface). ``[X, Y, Z]`` bool."""
    c = grid.centres().reshape(*grid.shape, 3)
    solid = (free == 0) & (seen >= min_seen) & (c[..., 2] > 0)
    if cube is not None:  # the cube is a solid too, known exactly: not the pot
        h = cube.size / 2 + grid.step
        solid &= ~((np.abs(c[..., 0]) < h) & (np.abs(c[..., 1]) < h) & (c[..., 2] < cube.size + grid.step))
    r = max(1, int(round(thickness / grid.step)))
    core = ndimage.binary_erosion(solid, _ball(r))
    labels, n = ndimage.label(core)
    if n == 0:
        return np.zeros(grid.shape, bool)
    near = np.linalg.norm(c[..., :2] - axis_xy, axis=-1) < near_axis
    keep = np.unique(labels[core & near])
    keep = keep[keep > 0]
    return ndimage.binary_dilation(np.isin(labels, keep), _ball(r + 1))


def _weigh_evidence(params: dict, mu: np.ndarray, candidate: np.ndarray, orbit_radius: float, cfg: DecideConfig,
                    sfm_distance: np.ndarray | None, needs_support: np.ndarray | None = None):
    """The candidates' colours and neighbours weighed (:func:`decide_plant`) against every opaque Gaussian that is no
    candidate; the plant's colours learned near the SfM points (``sfm_distance`` ``[N]``: each Gaussian's distance to
    the nearest; None: no points). ``needs_support`` ``[N]``: where the body's Gaussians too need an SfM point near."""
    rgb = sh_to_rgb(params["sh0"][:, 0, :]).clamp(0, 1).numpy().astype(np.float64)
    opacity = torch.sigmoid(params["opacities"]).numpy().reshape(-1).astype(np.float64)
    opaque = opacity > cfg.sure_opacity
    return decide_plant(mu, rgb, opacity, candidate, opaque & ~candidate, orbit_radius, sfm_distance, cfg,
                        needs_support)


def plant_top(params: dict, plant: np.ndarray) -> float | None:
    """The top of the decided plant: the :data:`TOP_PERCENTILE` percentile of its opaque Gaussians' heights (a few
    stray ones above it aside); None without any."""
    z = params["means"].numpy()[:, 2]
    sure = plant & (torch.sigmoid(params["opacities"]).numpy().reshape(-1) > TOP_OPACITY)
    return float(np.percentile(z[sure], TOP_PERCENTILE)) if sure.any() else None


def join_out_of_frame(mu: np.ndarray, plant: np.ndarray, pool: np.ndarray, link: float) -> np.ndarray:
    """The Gaussians of ``pool`` (indices into ``mu`` ``[N, 3]``) linked to the ``plant`` ``[N]`` bool Gaussians
    through Gaussians of ``pool``, each step shorter than ``link``. ``[N]`` bool"""
    joined = np.zeros(len(mu), bool)
    if not len(pool) or not plant.any():
        return joined
    tree = cKDTree(mu[pool])
    taken = np.zeros(len(pool), bool)
    frontier = mu[plant]
    while len(frontier):  # breadth first from the plant through the pool
        hits = {j for near in tree.query_ball_point(frontier, link) for j in near}
        new = np.array(sorted(j for j in hits if not taken[j]), int)
        taken[new] = True
        frontier = mu[pool[new]]
    joined[pool[taken]] = True
    return joined


def object_model(params: dict, views: list, cube: CubeSpec | None, sfm_points: np.ndarray, reach: float = 0.55,
                 min_in_view: float = 0.85, sfm_reach: float = 0.07, ground_cm: float = 1.0,
                 pot_margin_cm: float = 1.0, seed: int = 0, decide: DecideConfig | None = None,
                 opaque: float = 0.2, joined_in_view: float = 0.5, join_reach: float = 0.02) -> ObjectModel:
    """Which Gaussians of a whole-scene model are the plant (see the module docstring).

    ``params``: the model (``means`` ``[N, 3]`` ...); ``views``: its cameras (``train.data.View``);
    ``cube``: the calibration cube when the model is in its frame (cm, z up), else None;
    ``sfm_points`` ``[P, 3]``: the poses stage's triangulated points. The plant is looked for within
    ``reach`` times the cameras' median distance from the axis, above the ground by ``ground_cm``,
    outside the pot (found among the Gaussians more opaque than ``opaque``, grown by ``pot_margin_cm``) and the
    cube, in view in at least ``min_in_view`` of
    the frames, and within ``sfm_reach`` times the cameras' distance of an SfM point: a blank ceiling
    or wall can be drawn by Gaussians at any depth, and a quick model sometimes hangs a cloud of them
    above the plant, where structure from motion, which needs texture seen from several frames,
    finds nothing. Within that region, ``decide`` (default :class:`DecideConfig`) weighs each
    Gaussian's colour and its neighbours (:func:`plantsplat.segment.decide.decide_plant`);
    ``DecideConfig(enabled=False)`` decides by position alone. A Gaussian of the region in view in fewer frames
    than ``min_in_view`` but at least ``joined_in_view`` is plant when it joins the plant's body, within ``join_reach``
    times the cameras' distance of it or of another such Gaussian (:func:`join_out_of_frame`): a leaf tip that
    leaves the frames from the side.
    """
    c2ws = [np.linalg.inv(v.viewmat) for v in views]
    centre = orbit_axis(c2ws)
    up = np.array([0.0, 0.0, 1.0]) if cube is not None else up_from_orbit(c2ws, centre)
    mu = params["means"].numpy().astype(np.float64)
    rel = mu - centre
    height = rel @ up
    radial = np.linalg.norm(rel - np.outer(height, up), axis=1)
    cams = np.array([M[:3, 3] for M in c2ws]) - centre
    cam_radial = float(np.median(np.linalg.norm(cams - np.outer(cams @ up, up), axis=1)))
    region = radial < reach * cam_radial
    info: dict = {"axis": np.round(centre, 3).tolist(), "reach": round(reach * cam_radial, 3)}
    sfm_distance = cKDTree(sfm_points).query(mu)[0] if len(sfm_points) else None  # [N]
    if sfm_distance is not None:
        region &= sfm_distance < sfm_reach * cam_radial
    part = np.zeros(len(mu), np.int8)
    over_soil = None
    if cube is not None:
        region &= mu[:, 2] > ground_cm
        in_cube = in_cube_box(mu, cube.size, 0.5)
        region &= ~in_cube
        part[in_cube] = PART_NAMES.index("cube")
        solid = torch.sigmoid(params["opacities"]).numpy().reshape(-1) > opaque
        pot = find_pot(mu[solid], centre[:2], seed=seed, spread=horizontal_spread(params)[solid])
        if pot is not None:
            pot = with_sfm_soil(pot, sfm_points)
            in_pot = pot.contains(mu, pot_margin_cm)
            over_soil = pot.over_soil(mu)
            region &= ~in_pot
            part[in_pot] = PART_NAMES.index("pot")
            info["pot"] = pot.summary()
    candidate = np.zeros(len(mu), bool)
    idx = np.flatnonzero(region)
    share = in_view_share(mu[idx], views)
    candidate[idx] = share >= min_in_view
    plant = candidate
    decide = decide or DecideConfig()
    if decide.enabled:
        plant, info["decision"] = _weigh_evidence(params, mu, candidate, cam_radial, decide, sfm_distance, over_soil)
    joined = join_out_of_frame(mu, plant, idx[(share >= joined_in_view) & (share < min_in_view)], join_reach * cam_radial)
    plant = plant | joined
    info["joined_out_of_frame"] = int(joined.sum())
    part[candidate & ~plant] = PART_NAMES.index("set aside")
    part[plant] = PART_NAMES.index("plant")
    info["plant_gaussians"] = int(plant.sum())
    top = plant_top(params, plant)
    if cube is not None and top is not None:
        info["plant_top_cm"] = round(top, 2)
    return ObjectModel(params=params, plant=plant, cube=cube, axis=centre, up=up, info=info, part=part)

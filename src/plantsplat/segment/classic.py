"""The classic (offline, model-free) segmenter: plant colours + cube geometry + multi-view consistency.

Per capture (all frames at once):

1. **Markers and cameras.** ArUco markers are detected in every frame; the intrinsics are estimated
   from the cube's known 3D marker corners (:func:`geometry.estimate_intrinsics`) and each frame's
   camera pose in the cube frame is solved. One-marker poses that disagree with the orbit through
   their neighbours (flips) are dropped (poses from two or more markers are kept), and every frame
   without a pose gets one on the orbit (:func:`geometry.fill_orbit_poses`: angle, radius and height about the orbit's vertical axis
   interpolated between the nearest posed frames in video order, orientation by slerp; the ends
   extrapolated). So the cube is drawn, and the plant located in 3D, in every frame.
2. **Where the plant is.** The camera circles the plant, so the point closest to every optical axis
   (the orbit centre) lies in the plant. A coarse visual hull is carved from the frames' strong
   plant-colour masks; its 3D connected component on the vertical axis through the orbit centre
   (plus pieces within a couple of centimetres) is the plant. Green objects elsewhere in the room
   (decoys, posters, other plants) are other components and are dropped in 3D, whatever their colour.
   A plant-coloured pot shows up in the hull as a solid block on the ground whose horizontal sections
   are filled discs (leaves are thin): :func:`geometry.find_pot` fits a frustum to it; its voxels
   leave the plant hull, its silhouette leaves the plant region wherever no plant voxel lies in front
   of it, and it hides the cube where the cube stands behind it. Thin runs that stand out from the image on
   both sides (:func:`ridge_contrast`) are carved into a stem hull; where it joins the plant it is stem,
   whatever its colour.
3. **Per frame.** The plant's hull is projected (with a margin) as the region of interest. Inside it,
   plant colours are taken with hysteresis (strong seeds grow into weak pixels; weak red only from
   strong red fruit, so dark red walls next to leaves are not grown into), small pale blobs
   touching the plant (flowers) are added, and so are thin runs of weak or stem colour (olive,
   brown, red-brown petioles) touching it whose colour is not the room's; where the fruit hull (red of any
   brightness, or fruit-sized pieces of unripe cream-green) projects, pieces of fruit colour lying mostly there are
   added even when the room shows that colour; specks are removed and pinholes filled. The cube is added
   as its exact projected silhouette (all six faces, also where no marker is visible).

Without a usable cube (no markers, or too few poses) step 2 falls back to 2D: the plant is the
large plant-coloured region nearest the image centre in each frame.

Example:
    >>> seg = ClassicSegmenter()
    >>> ctx = seg.analyse(["ws/images/frame_00000.png", ...])
    >>> mask, info = seg.mask(0, rgb, ctx)      # bool [H, W]
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from plantsplat.cube import CubeSpec
from plantsplat.markers import detect_markers
from plantsplat.io import read_image
from plantsplat.log import get_logger, progress
from plantsplat.segment import geometry as geo
from plantsplat.segment.colour import ColourModel, plant_colour_masks, stem_colour_mask, unripe_colour_mask

log = get_logger(__name__)


@dataclass(frozen=True)
class ClassicSettings:
    """Settings of the classic segmenter (defaults suit phone captures at 540x960 to 1080x1920)."""

    colour: ColourModel = field(default_factory=ColourModel)
    cube: CubeSpec = field(default_factory=CubeSpec)
    use_cube: bool = True
    """Use the cube: its silhouette is foreground, and its poses locate the plant in 3D."""
    analysis_size: int = 240
    """Longer side (px) of the downscaled masks used for the visual hull and 2D analysis."""
    hull_voxels: int = 72
    """Voxels along each horizontal side of the visual-hull grid."""
    hull_keep_fraction: float = 0.9
    """A voxel is plant when it falls on plant colour in at least this fraction of the views seeing it."""
    roi_voxels: int = 100
    """Voxels along each horizontal side of the finer grid that carves the plant region again (gaps between leaves);
    at most ``hull_voxels``: no second carving."""
    roi_margin_cm: float = 0.75
    """Margin (cm) around the projected plant hull inside which plant-coloured pixels are accepted."""
    join_gap_cm: float = 3.0
    """Hull pieces within this distance (cm) of the plant belong to it (separated leaves, fruit)."""
    weak_band: float = 0.003
    """Weak plant colours are accepted only this far (fraction of the longer image side) from strong ones."""
    stem_px: float = 4.0
    """Runs of weak plant colour or stem colour (olive, brown, red-brown) thinner than about twice this (px at 960) that
    touch the plant are plant (petioles, peduncles, runners; wide soil, wood and pot regions of those colours are not),
    unless their colour is one of the capture's background colours (so only where the plant was located in 3D and the
    background learned); 0 = off. On the benchmark's synthetic seeds 0-4 (48 frames): petiole recall 0.63 -> 0.71,
    mean IoU 0.841 -> 0.848. Without the background colours it took the grain of a real brown floor (ROMI real plant)."""
    pale_max_area: float = 0.004
    """Largest weak/pale blob touching the plant accepted whole (unripe fruit, flower), as a fraction of the image."""
    min_blob: float = 2e-5
    """Plant pieces smaller than this fraction of the image are dropped as specks."""
    fill_holes: float = 1.5e-4
    """Holes smaller than this fraction of the image are filled."""
    feature_size: int = 0
    """Longer side (px) of the gray frames used to locate frames without visible markers (SIFT + PnP); 0 = off."""
    cube_from_features: bool = True
    """Draw the cube also in frames located by features (not by their own markers)."""
    roi_max_gap: int = 4
    """Frames without any pose borrow one interpolated over at most this many frames (plant region only)."""
    min_poses: int = 6
    """Fewer frames with a cube pose than this: fall back to the 2D plant locator."""
    remove_pot: bool = True
    """Find a plant-coloured pot (a solid disc-sectioned block on the ground in the visual hull) and leave it out."""
    fruit_keep_fraction: float = 0.5
    """Keep fraction of the second hull carved from fruit colours alone (fruit partly hidden by the pot)."""
    fruit_reach: float = 0.3
    """Fruit hull pieces within this fraction of the orbit radius of the orbit axis are fruit of the plant."""
    fruit_inside: float = 0.6
    """A piece of fruit colour is fruit when at least this fraction of it lies where the fruit hull projects."""
    unripe_fruit_cm: float = 7.0
    """Largest thickness (cm) of a piece of the hull carved from unripe-fruit colour (pale yellow-green to cream,
    :func:`~plantsplat.segment.colour.unripe_colour_mask`) that counts as fruit, whose length may reach twice this (fruit
    side by side, :func:`~plantsplat.segment.geometry.fruit_sized`); thicker or longer pieces (a beige pot, wall or box)
    do not; 0 = off. (A limit on the longest side instead left out two unripe fruit touching, 9.6 cm, and one fruit's
    hull, 7.4 cm, on the benchmark's seeds 2 and 4.)"""
    cube_occlusion: bool = True
    """Compare each frame with the cube's printed faces as the camera should see them, and leave out of the cube what
    hides it (the pot, a leaf, a hand)."""
    learn_background: bool = True
    """Learn the capture's background colours (around the plant's projected hull, and the pot) and reject plant-coloured
    pixels of those colours inside the plant region (green objects seen through gaps between leaves, green pots)."""
    background_ring: float = 0.05
    """Width of the band around the plant region whose colours are background, as a fraction of the longer image side."""
    stem_contrast: float = 12.0
    """Stems seen in 3D: pixels of weak plant or stem colour whose colour differs by more than this (CIELAB distance,
    OpenCV 8-bit units) from the image on both sides across their local orientation (:func:`ridge_contrast`), in long
    thin runs, are stem candidates: olive or brown petioles against a wall of the same colours, which the colour rules
    above leave out as background. The hull carved from the candidates alone keeps what lines up in 3D over the orbit
    (``stem_keep_fraction``); its pieces joined to the plant's hull, above the floor and outside the pot, are stems,
    and where they project the candidates touching the plant are added. Posts, wood grain, tile joints and the edges of
    objects behind the plant lie elsewhere from other views and are carved away; 0 = off. Chosen on the benchmark's
    seeds 0-4 (120 frames 540x960): mean IoU 0.8655 -> 0.8717 (seed 0, olive petioles against an olive wall: 0.802 ->
    0.832; the others within 0.002); on seeds 10-14, not used to choose it: 0.8927 -> 0.8919."""
    stem_keep_fraction: float = 0.5
    """Keep fraction of the hull carved from the stem candidates (leaves hide stems from part of the orbit; runs of
    texture do not line up)."""
    thin_px: float = 3.0
    """Runs of background colour thinner than about twice this (px at 960) are kept (stems, peduncles)."""
    edge_radius: float = 2.0
    """Radius (px at 960) of the guided filter that moves the plant mask's outline onto the image's edges; 0 = off."""
    edge_eps: float = 1e-3
    """Regulariser of that guided filter (gray levels in [0, 1]): smaller follows weaker edges."""
    background_ratio: float = 1.0
    """A colour is background when it is seen this many times more often around the plant (or on the pot) than inside it."""
    background_outside: float = 3.0
    """Weight of the colours of the rest of each frame (outside the plant region), by share: a colour is background also
    when its share of the rest of the frames, times this, exceeds its share of the plant region; 0 = the band alone.
    Measured on synthetic captures of seeds 10-17 (chosen on these, not the benchmark's): mean IoU 0.851 at 0, 0.858 at
    1, 0.867 at 3, 0.861 at 10; then on the benchmark's seeds 0-4: 0.835 at 0, 0.841 at 3 (fewer background pixels
    taken, 7.1 -> 4.0 %, more plant pixels missed, 9.4 -> 11.0 %: a room with green walls loses leaf colours)."""


@dataclass
class CaptureContext:
    """What :meth:`ClassicSegmenter.analyse` learns from all frames."""

    size: tuple[int, int]  # (w, h) of the frames
    detections: list[dict[int, np.ndarray]]
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    poses: list[np.ndarray | None] = field(default_factory=list)
    pose_source: list[str] = field(default_factory=list)
    roi_poses: list[np.ndarray | None] = field(default_factory=list)  # poses, gaps bridged loosely
    hull_points: np.ndarray | None = None  # [M, 3] plant voxel centres (cube frame, cm)
    fruit_points: np.ndarray | None = None  # [F, 3] the fruit hull's points among them (cube frame, cm)
    stem_points: np.ndarray | None = None  # [S, 3] voxel centres of stems seen in 3D (cube frame, cm)
    stem_voxel: float = 0.0
    pot: dict[str, Any] | None = None  # plant-coloured pot frustum (geometry.find_pot), left out of the masks
    voxel: float = 0.0
    centre: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)


_CROP_MARGIN = 24  # px at 960 around the plant region's box: more than any filter reaches (thin runs 7, guided 4)


def _crop_box(roi_small: np.ndarray, W: int, H: int, margin: int) -> tuple[int, int, int, int] | None:
    """Box ``(x0, y0, x1, y1)`` of the frame (``W`` x ``H``) covering the pixels that the small region mask
    ``roi_small`` marks (as a nearest-neighbour upscale maps them), plus ``margin`` px; None when it is empty."""
    ys, xs = np.nonzero(roi_small)
    if len(xs) == 0:
        return None
    h, w = roi_small.shape
    # full-size pixel X maps to small pixel floor(X w / W): small column c covers X in [c W / w, (c + 1) W / w)
    x0 = max(0, int(np.floor(xs.min() * W / w)) - margin)
    x1 = min(W, int(np.ceil((xs.max() + 1) * W / w)) + margin)
    y0 = max(0, int(np.floor(ys.min() * H / h)) - margin)
    y1 = min(H, int(np.ceil((ys.max() + 1) * H / h)) + margin)
    return x0, y0, x1, y1


_YSHIFT, _CSHIFT = 4, 2  # colour bins: 16 luma x 64 x 64 chroma levels (YCrCb)
_NBINS = (256 >> _YSHIFT) * (256 >> _CSHIFT) ** 2


def _colour_bins(rgb: np.ndarray) -> np.ndarray:
    """Colour-histogram bin of every pixel of an RGB uint8 image: int ``[H, W]`` in ``[0, _NBINS)``."""
    import cv2

    ycc = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2YCrCb)
    nc = 256 >> _CSHIFT
    return ((ycc[..., 0] >> _YSHIFT).astype(np.int32) * nc + (ycc[..., 1] >> _CSHIFT)) * nc + (ycc[..., 2] >> _CSHIFT)


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Edge-preserving smoothing of ``src`` steered by a gray ``guide`` (both float32 ``[H, W]``): the guided filter of
    He, Sun and Tang (ECCV 2010), a local linear model ``src ~ a * guide + b`` fitted in ``(2 radius + 1)^2`` windows
    with regulariser ``eps``, computed with OpenCV box filters."""
    import cv2

    k = (2 * radius + 1, 2 * radius + 1)

    def box(x):
        return cv2.boxFilter(x, -1, k, borderType=cv2.BORDER_REFLECT)

    mean_i, mean_p = box(guide), box(src)
    var_i = box(guide * guide) - mean_i * mean_i
    a = (box(guide * src) - mean_i * mean_p) / (var_i + eps)
    b = mean_p - a * mean_i
    return box(a) * guide + box(b)


_RIDGE_REACH = (2.0, 4.0, 7.0)  # px at 960: how far to each side a stem's flanks are looked for (thin to thick stems)
_RIDGE_COHERENCE = 0.65  # a run has one direction: the colour structure tensor's coherence is at least this
_RIDGE_SPAN = 4.0  # a run is at least this many times longer than the widest stem (``stem_px``)


def ridge_contrast(rgb: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """How much each pixel of an RGB uint8 image stands out from *both* sides of a thin run through it.

    The local orientation comes from the colour structure tensor (CIELAB, smoothed); across it, the pixel's colour is
    compared with the colours ``d`` px away on either side, for each reach ``d`` in :data:`_RIDGE_REACH` (px at 960,
    times ``scale``). The score is the square root of the dot product of the two colour differences (flank minus
    centre; 0 where negative), best over the reaches: about the colour distance to the flanks on a stem or a wire
    (both flanks differ the same way), low inside a wide region and on an edge (one flank is alike, or, at an edge's
    blurred middle, the flanks differ in opposite ways), and on noise (smoothed away); 0 where the local gradients
    have no one direction (texture, specks, corners). Returns ``(score float32 [H, W], flank float32 [2, H, W])``:
    ``flank`` is the (x, y) offset from each pixel to one side at its best reach (the other side is at minus it).
    """
    import cv2

    lab = cv2.GaussianBlur(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2LAB).astype(np.float32), (0, 0),
                           max(0.5, scale))
    ones = np.ones((1, 3), np.float32)  # sums the three channels
    gx = cv2.Sobel(lab, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lab, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jxy, jyy = (cv2.transform(a * b, ones) for a, b in ((gx, gx), (gx, gy), (gy, gy)))
    sig = 4.0 * max(scale, 0.25)
    jxx, jxy, jyy = (cv2.GaussianBlur(j, (0, 0), sig) for j in (jxx, jxy, jyy))
    # the tensor's main eigenvector: the direction of strongest change, across a run
    diff = jxx - jyy
    root = np.sqrt(diff * diff + 4 * jxy * jxy)
    ex = diff + root
    ey = 2 * jxy
    flat = ex * ex + ey * ey < 1e-12  # jxx <= jyy with no cross term: the change is along y
    ex[flat] = 0.0
    ey[flat] = 1.0
    length = np.sqrt(ex * ex + ey * ey)
    nx, ny = ex / length, ey / length
    h, w = jxx.shape
    xx, yy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    best = np.zeros((h, w), np.float32)  # squared until the end
    reach = np.zeros((h, w), np.float32)
    for d in _RIDGE_REACH:
        d = max(1.0, d * scale)
        a, b = (cv2.remap(lab, xx + sg * nx, yy + sg * ny, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT) - lab
                for sg in (-d, d))
        sc = cv2.transform(a * b, ones)  # (flank1 - centre) . (flank2 - centre): negative across an edge
        up = sc > best
        best[up] = sc[up]
        reach[up] = d
    best = np.sqrt(best)
    best[root < _RIDGE_COHERENCE * (jxx + jyy + 1e-6)] = 0.0  # no one direction (texture, specks, corners): no run
    return best, np.stack([nx * reach, ny * reach])


def thread_map(fn, items: list, workers: int | None = None):
    """``map(fn, items)`` in order on a pool of threads (one per core, at most 4): OpenCV and numpy release the GIL
    in their heavy loops, so frames are processed side by side. At most ``2 * workers`` results wait unconsumed."""
    from concurrent.futures import ThreadPoolExecutor

    workers = workers or max(1, min(4, os.cpu_count() or 1))
    if workers == 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(workers) as ex:
        pending = []
        it = iter(items)
        for x in it:
            pending.append(ex.submit(fn, x))
            if len(pending) >= 2 * workers:
                break
        for x in it:
            yield pending.pop(0).result()
            pending.append(ex.submit(fn, x))
        for f in pending:
            yield f.result()


def _small_size(w: int, h: int, longest: int) -> tuple[int, int, float]:
    s = min(1.0, longest / max(w, h))
    return max(1, int(round(w * s))), max(1, int(round(h * s))), s


def _components_with(mask: np.ndarray, marker: np.ndarray) -> np.ndarray:
    """The 8-connected components of the bool ``mask`` that contain a pixel of ``marker``: bool, same shape."""
    import cv2

    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    ok = np.zeros(n, bool)
    ok[np.unique(lab[marker & mask])] = True
    ok[0] = False
    return ok[lab]


def _thin_runs(mask: np.ndarray, r: int, close: int = 0) -> np.ndarray:
    """The pixels of the bool ``mask`` not within a pixel of what survives an opening by a disk of radius ``r``: its
    runs thinner than about ``2 r`` px (stems), without the wide regions (soil, wood, a wall). With ``close`` > 0 the
    mask is first closed by a disk of that radius, so that a wide region broken into thin pieces by specks of another
    colour (soil with grit or perlite) still counts as wide. bool, same shape."""
    import cv2

    m8 = mask.astype(np.uint8)
    if close > 0:
        m8 = cv2.morphologyEx(m8, cv2.MORPH_CLOSE, _disk(close))
    wide = cv2.dilate(cv2.morphologyEx(m8, cv2.MORPH_OPEN, _disk(r)), _disk(1))
    return mask & (wide == 0)


def _disk(r: float):
    import cv2

    r = max(0, int(round(r)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


class ClassicSegmenter:
    """Offline plant + cube segmenter (see the module docstring for the method)."""

    def __init__(self, settings: ClassicSettings = ClassicSettings()):
        self.s = settings

    # ---------------------------------------------------------------- pass 1: the whole capture
    def analyse(self, image_paths: list[Path], keep_bytes: int = 0,
                markers: dict[str, dict[int, np.ndarray]] | None = None) -> CaptureContext:
        """Read every frame once: markers, strong colour masks, cameras, the plant's visual hull. The first frames,
        up to ``keep_bytes`` of them, stay decoded in :attr:`frames` (index -> RGB) for the per-frame pass.
        ``markers``: the capture's detections by frame name (``markers.json``); without them each frame is searched."""
        import cv2

        s = self.s
        dets: list[dict[int, np.ndarray]] = []
        smalls: list[np.ndarray] = []
        small_rgb: list[np.ndarray] = []
        red_smalls: list[np.ndarray] = []
        unripe_smalls: list[np.ndarray] = []
        grays: list[np.ndarray] = []
        size = None
        self.frames: dict[int, np.ndarray] = {}

        def one(p: Path):
            rgb = read_image(p)
            h, w = rgb.shape[:2]
            if not s.use_cube:
                det = {}
            elif markers is not None:
                det = markers.get(Path(p).name, {})
            else:
                det = detect_markers(rgb, s.cube)
            sw, sh, _ = _small_size(w, h, s.analysis_size)
            half = cv2.resize(rgb, (2 * sw, 2 * sh), interpolation=cv2.INTER_AREA)  # colours at twice the analysis size
            strong, weak, _, red = plant_colour_masks(half, s.colour, with_red=True)
            k3 = np.ones((3, 3), np.uint8)
            red = cv2.morphologyEx(red.astype(np.uint8), cv2.MORPH_OPEN, k3)
            red_small = cv2.resize(red * 255, (sw, sh), interpolation=cv2.INTER_AREA) >= 64
            unripe_small = None
            if s.unripe_fruit_cm > 0:
                unripe = cv2.morphologyEx(unripe_colour_mask(half, s.colour).astype(np.uint8), cv2.MORPH_OPEN, k3)
                unripe_small = cv2.resize(unripe * 255, (sw, sh), interpolation=cv2.INTER_AREA) >= 64
            small = cv2.resize(strong.astype(np.uint8) * 255, (sw, sh), interpolation=cv2.INTER_AREA) >= 48
            stem_small = None
            if s.stem_contrast > 0 and det:  # stems are carved from the frames with markers (those with a pose)
                stems = self._stem_candidates(half, weak, max(half.shape[:2]) / 960)
                stem_small = cv2.resize(stems.astype(np.uint8) * 255, (sw, sh), interpolation=cv2.INTER_AREA) >= 48
            gray = None
            if s.feature_size:
                fw, fh, _ = _small_size(w, h, s.feature_size)
                gray = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (fw, fh), interpolation=cv2.INTER_AREA)
            return (p, (w, h), det, small, cv2.resize(half, (sw, sh), interpolation=cv2.INTER_AREA), red_small,
                    unripe_small, stem_small, gray, rgb)

        stem_smalls: list[np.ndarray | None] = []
        for i, (p, wh, det, small, srgb, red_small, unripe_small, stem_small, gray, rgb) in enumerate(progress(
                thread_map(one, image_paths), "segment: markers and colours", total=len(image_paths))):
            if size is None:
                size = wh
            elif wh != size:
                from plantsplat.errors import PlantsplatError

                raise PlantsplatError(f"{p}: size {wh[0]}x{wh[1]} differs from the other frames' {size[0]}x{size[1]}; "
                                      "re-run `plantsplat frames`")
            if rgb.nbytes * (i + 1) <= keep_bytes:
                self.frames[i] = rgb
            dets.append(det)
            smalls.append(small)
            small_rgb.append(srgb)
            red_smalls.append(red_small)
            unripe_smalls.append(unripe_small)
            stem_smalls.append(stem_small)
            if gray is not None:
                grays.append(gray)
        assert size is not None
        ctx = CaptureContext(size=size, detections=dets)
        ctx.info["frames_with_markers"] = int(sum(1 for d in dets if d))
        self._red_smalls = red_smalls
        self._unripe_smalls = unripe_smalls
        self._stem_smalls = stem_smalls
        if s.use_cube:
            self._geometry(ctx, smalls, grays)
        ctx.info["plant_locator"] = "3d" if ctx.hull_points is not None else "2d"
        self._smalls = smalls
        self._small_rgb = small_rgb
        self._bg_learned = False
        if ctx.hull_points is not None and s.learn_background:
            self._learn_background(ctx)
        return ctx

    def _stem_candidates(self, rgb: np.ndarray, weak: np.ndarray, scale: float,
                         plant: np.ndarray | None = None) -> np.ndarray:
        """Thin runs of an RGB image ``[H, W, 3]`` that could be stems: pixels of weak plant or stem colour (``weak``
        is the weak plant-colour mask) that stand out from both flanks (:func:`ridge_contrast` above
        ``stem_contrast``), in runs thinner than about twice ``stem_px`` (``scale``: the image's longer side / 960).
        With a ``plant`` mask, pixels whose two flanks are both plant (a gap between leaves) are left out."""
        import cv2

        s = self.s
        score, flank = ridge_contrast(rgb, scale)
        cand = (score > s.stem_contrast) & (weak | stem_colour_mask(rgb, s.colour))
        if plant is not None:
            h, w = plant.shape
            xx, yy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            pf = plant.astype(np.uint8)
            step = flank * (1.0 + 1.0 / np.maximum(np.hypot(flank[0], flank[1]), 1e-6))  # one pixel beyond the reach
            sides = [cv2.remap(pf, xx + sg * step[0], yy + sg * step[1], cv2.INTER_NEAREST) > 0 for sg in (-1.0, 1.0)]
            cand &= ~(sides[0] & sides[1])
        r = max(1, int(round(s.stem_px * scale)))
        # runs, not specks: long (a stem's length is many times its width) and sparse in their bounding box
        n, lab, st, _ = cv2.connectedComponentsWithStats(_thin_runs(cand, r).astype(np.uint8), connectivity=8)
        span = np.maximum(st[:, cv2.CC_STAT_WIDTH], st[:, cv2.CC_STAT_HEIGHT]).astype(np.float64)
        ok = (span >= _RIDGE_SPAN * (2 * r + 1)) & (st[:, cv2.CC_STAT_AREA] <= 0.3 * span * span)
        ok[0] = False
        return ok[lab]

    def _geometry(self, ctx: CaptureContext, smalls: list[np.ndarray], grays: list[np.ndarray]) -> None:
        import cv2
        from scipy import ndimage

        s = self.s
        est = geo.estimate_intrinsics(ctx.detections, ctx.size, s.cube)
        if est is None:
            log.warning("segment: the cube's markers were found in fewer than 3 frames; locating the plant in 2D")
            return
        ctx.K, ctx.dist, kinfo = est
        ctx.info["intrinsics"] = kinfo
        ctx.poses, rms, ctx.pose_source = geo.cube_poses(ctx.detections, ctx.K, ctx.dist, s.cube)
        n_marker_pose = sum(p is not None for p in ctx.poses)
        if s.feature_size and grays and n_marker_pose >= 2 and n_marker_pose < len(ctx.poses):
            fw, fh, fs = _small_size(*ctx.size, s.feature_size)
            Kf = ctx.K.copy()
            Kf[:2] *= fs
            Kf[0, 2] = (ctx.K[0, 2] + 0.5) * fs - 0.5
            Kf[1, 2] = (ctx.K[1, 2] + 0.5) * fs - 0.5
            log.info("segment: locating %d frames without markers from image features", len(ctx.poses) - n_marker_pose)
            ctx.poses, found = geo.poses_from_features(grays, ctx.poses, Kf)
            ctx.pose_source = ["features" if f else h for f, h in zip(found, ctx.pose_source)]
            ctx.info["frames_with_feature_pose"] = int(sum(found))
        n_pose = sum(p is not None for p in ctx.poses)
        ctx.info["frames_with_cube_pose"] = n_pose
        ctx.roi_poses = geo.interpolate_gaps(ctx.poses, s.roi_max_gap, 90.0)
        ctx.info["frames_with_interpolated_pose"] = sum(h == "interpolated" for h in ctx.pose_source)
        good = [r for r in rms if r is not None]
        ctx.info["cube_pose_rms_px_median"] = round(float(np.median(good)), 4) if good else None
        if n_pose < s.min_poses:
            log.warning("segment: a cube pose in only %d frames; locating the plant in 2D", n_pose)
            return
        centre = geo.orbit_centre(ctx.poses)
        cams = np.array([np.linalg.inv(T)[:3, 3] for T in ctx.poses if T is not None])  # [P, 3]
        if centre is None:
            log.warning("segment: the camera does not circle a point; locating the plant in 2D")
            return
        # poses that disagree with the orbit through their neighbours (one-marker flips) are dropped
        multi = [j for j, (d, h) in enumerate(zip(ctx.detections, ctx.pose_source)) if h == "markers" and len(d) >= 2]
        bad = geo.orbit_outliers(ctx.poses, centre, keep=multi)
        for j in bad:
            ctx.poses[j] = None
            ctx.pose_source[j] = "none"
        ctx.info["frames_with_rejected_pose"] = len(bad)
        ctx.info["frames_with_cube_pose"] = n_pose - len(bad)
        # every frame gets a camera: gaps interpolated along the orbit, ends extrapolated
        ctx.roi_poses, filled = geo.fill_orbit_poses(ctx.poses, centre)
        ctx.pose_source = ["orbit" if f else h for f, h in zip(filled, ctx.pose_source)]
        ctx.info["frames_with_orbit_pose"] = int(sum(filled))
        horiz = np.hypot(cams[:, 0] - centre[0], cams[:, 1] - centre[1])
        D = float(np.median(horiz))
        depth = float(np.median(np.linalg.norm(cams - centre, axis=1)))
        radius = 0.6 * D
        z_hi = max(float(cams[:, 2].max()), 2 * float(centre[2])) + 0.3 * D
        sw, sh, sc = _small_size(*ctx.size, s.analysis_size)
        Ks = ctx.K.copy()
        Ks[:2] *= sc
        Ks[0, 2] = (ctx.K[0, 2] + 0.5) * sc - 0.5
        Ks[1, 2] = (ctx.K[1, 2] + 0.5) * sc - 0.5

        def carve(masks: list[np.ndarray], voxels: int, keep: float):
            """Visual hull around the orbit centre, ``voxels`` a side, of the posed frames' ``masks`` (analysis size),
            each dilated by a voxel's reach: :func:`geometry.visual_hull`'s ``(occupied, origin, voxel size)``."""
            kernel = _disk(np.ceil(0.87 * (2 * radius / voxels) * Ks[0, 0] / depth))
            grown = [cv2.dilate(m.astype(np.uint8), kernel).astype(bool)
                     if ctx.poses[j] is not None and m is not None else None for j, m in enumerate(masks)]
            return geo.visual_hull(grown, ctx.poses, Ks, centre, radius, (-0.05 * D, z_hi), voxels, keep)

        log.info("segment: carving the plant's visual hull from %d views", n_pose)
        occ, origin, vs = carve(smalls, s.hull_voxels, s.hull_keep_fraction)
        plant = geo.plant_component(occ, origin, vs, centre[:2], 0.12 * D, s.join_gap_cm)
        if s.fruit_keep_fraction < s.hull_keep_fraction:
            # fruit hang beside the pot, which hides them from part of the orbit: carved with a lower keep fraction
            # from red alone (of any brightness: shaded fruit are too dark to seed the plant; a colour rooms rarely
            # show near a plant), they join the plant when they hang within fruit_reach of the orbit axis, above the
            # ground and below the plant's top
            rocc, _, _ = carve(self._red_smalls, s.hull_voxels, s.fruit_keep_fraction)
            xs = origin[0] + np.arange(rocc.shape[0]) * vs
            ys = origin[1] + np.arange(rocc.shape[1]) * vs
            zs = origin[2] + np.arange(rocc.shape[2]) * vs
            near = ((xs[:, None] - centre[0]) ** 2 + (ys[None, :] - centre[1]) ** 2 <= (s.fruit_reach * D) ** 2)
            top = zs[np.argwhere(plant)[:, 2]].max() if plant.any() else -np.inf
            hanging = near[:, :, None] & ((zs > -vs) & (zs <= top))[None, None, :]  # where fruit of the plant hang
            fruit = rocc & hanging & ~plant
            if s.unripe_fruit_cm > 0:
                # unripe fruit: the same from pale yellow-green to cream, a colour rooms often show (beige walls,
                # wood, boxes, pots), so only pieces no thicker than a fruit count (a truss of them may be longer)
                uocc, _, _ = carve(self._unripe_smalls, s.hull_voxels, s.fruit_keep_fraction)
                uocc &= hanging
                fruit |= geo.fruit_sized(uocc, vs, s.unripe_fruit_cm)
                ctx.info["hull_voxels_unripe"] = int(uocc.sum())
            ctx.info["hull_voxels_fruit"] = int(fruit.sum())
            plant |= fruit
        else:
            fruit = np.zeros_like(plant)
        idx = np.argwhere(plant)
        ctx.info.update(orbit_centre=centre.round(3), orbit_radius_cm=round(D, 2), hull_voxel_cm=round(vs, 3),
                        hull_voxels_total=int(occ.sum()), hull_voxels_plant=int(len(idx)))
        if len(idx) == 0:
            log.warning("segment: no plant-coloured volume found around the orbit centre; locating the plant in 2D")
            return
        pot = geo.find_pot(plant, origin, vs) if s.remove_pot else None
        pts = np.zeros((0, 3))
        if s.roi_voxels > s.hull_voxels:
            # the plant region is carved again on a finer grid (within the coarse plant and its fruit), so
            # that gaps between leaves, where the room shows through, leave the region
            focc, forigin, fvs = carve(smalls, s.roi_voxels, s.hull_keep_fraction)
            fidx = np.argwhere(focc)
            fpts = forigin + fidx * fvs
            cidx = np.clip(np.round((fpts - origin) / vs).astype(np.int64), 0, np.array(plant.shape) - 1)
            near = ndimage.binary_dilation(plant, iterations=1)
            fpts = fpts[near[cidx[:, 0], cidx[:, 1], cidx[:, 2]]]
            if s.fruit_keep_fraction < s.hull_keep_fraction and ctx.info.get("hull_voxels_fruit"):
                # the fruit hull's voxels (carved with a lower keep fraction) are kept whole, as fine points
                sub = (np.arange(int(round(vs / fvs))) + 0.5) * (vs / max(int(round(vs / fvs)), 1)) - vs / 2
                offs = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
                fr = origin + np.argwhere(fruit) * vs
                ctx.fruit_points = (fr[:, None, :] + offs[None]).reshape(-1, 3)
                fpts = np.concatenate([fpts, ctx.fruit_points])
            ctx.info["roi_voxel_cm"] = round(fvs, 3)
            pts, vs_roi = fpts, fvs
        if s.roi_voxels <= s.hull_voxels or len(pts) == 0:  # no finer carving, or it left nothing: the coarse volume
            pts, vs_roi = origin + idx * vs, vs  # [M, 3]
        if pot is not None:
            pts = pts[~geo.pot_inside(pts, pot, margin=1.5 * vs)]  # the hull is about a voxel fatter
            ctx.info["pot"] = {"axis": np.round(pot["axis"], 2).tolist(), "z_cm": np.round(pot["z"], 2).tolist(),
                               "r_cm": np.round(pot["r"], 2).tolist()}
            log.info("segment: plant-coloured pot found (rim at %.1f cm, radius %.1f cm); left out", pot["z"][1],
                     pot["r"][1])
        if s.stem_contrast > 0:
            # stems: the hull carved from the thin runs that stand out from their flanks alone, where it joins the
            # plant's hull, outside that hull, above the floor and outside the pot. Posts, wood grain and object edges
            # behind the plant lie elsewhere from other views and are carved away
            socc, _, _ = carve(self._stem_smalls, s.hull_voxels, s.stem_keep_fraction)
            lab, _ = ndimage.label(socc | plant, structure=np.ones((3, 3, 3)))
            joined = np.isin(lab, np.unique(lab[plant]))
            joined[lab == 0] = False
            stem = joined & socc & ~plant
            stem[:, :, : int(np.ceil((2 * vs - origin[2]) / vs))] = False  # the floor's lines and grain are not stems
            if pot is not None:
                sidx = np.argwhere(stem)
                inside = geo.pot_inside(origin + sidx * vs, pot, margin=vs)
                stem[tuple(sidx[inside].T)] = False
            ctx.stem_points = origin + np.argwhere(stem) * vs
            ctx.stem_voxel = vs
            ctx.info["hull_voxels_stem"] = int(stem.sum())
        ctx.pot = pot
        ctx.hull_points = pts
        ctx.voxel = vs_roi
        ctx.centre = centre
        self._Ks = Ks

    # ---------------------------------------------------------------- pass 2: one frame
    def _learn_background(self, ctx: CaptureContext) -> None:
        """Colour histograms of the plant region and of its surroundings over all frames -> a background-colour table.

        Inside the projected hull lie the plant and whatever shows through its gaps; around it lies the background
        (walls, floor, green objects of the room, which move through the plant region as the camera circles, but
        spend most frames outside it). A colour counted more often around the plant (and on a found pot) than
        inside it is background, and so is one whose share of the rest of the frames is large against its share inside
        (``background_outside``); plant-coloured pixels of such colours seed and grow nothing.
        """
        import cv2
        from scipy.ndimage import gaussian_filter

        s = self.s
        n_in = np.zeros(_NBINS, np.float64)
        n_ring = np.zeros(_NBINS, np.float64)
        n_pot = np.zeros(_NBINS, np.float64)
        n_out = np.zeros(_NBINS, np.float64)
        for i, small in enumerate(self._small_rgb):
            roi = self._roi_3d(i, ctx)
            if roi is None:
                continue
            h, w = roi.shape
            q = _colour_bins(small)
            inside = roi
            if ctx.pot is not None:
                pot = geo.pot_silhouette(ctx.pot, ctx.roi_poses[i], self._Ks, (w, h))
                n_pot += np.bincount(q[pot], minlength=_NBINS)
                inside = roi & ~pot
            n_in += np.bincount(q[inside], minlength=_NBINS)
            if s.background_ring > 0:
                ring = cv2.dilate(roi.astype(np.uint8), _disk(s.background_ring * max(h, w))).astype(bool) & ~roi
                n_ring += np.bincount(q[ring], minlength=_NBINS)
            if s.background_outside > 0:
                n_out += np.bincount(q[~roi], minlength=_NBINS)
        shape = (256 >> _YSHIFT, 256 >> _CSHIFT, 256 >> _CSHIFT)
        if s.background_outside > 0 and n_out.sum() > 0:
            # the rest of the frame counts by colour share: a colour s times rarer there than inside still counts as
            # background (a green box behind the plant in some frames fills a larger share of the rest of the room)
            n_ring = n_ring + n_out * (s.background_outside * n_in.sum() / n_out.sum())
        n_in = gaussian_filter(n_in.reshape(shape), 1.0).ravel()
        self._bg_ring = gaussian_filter(n_ring.reshape(shape), 1.0).ravel() > s.background_ratio * n_in
        self._bg_pot = gaussian_filter(n_pot.reshape(shape), 1.0).ravel() > s.background_ratio * n_in
        self._bg_learned = True
        ctx.info["background_colour_bins"] = int(self._bg_ring.sum())
        ctx.info["pot_colour_bins"] = int(self._bg_pot.sum())

    def _roi_3d(self, i: int, ctx: CaptureContext, points: np.ndarray | None = None,
                margin_cm: float | None = None) -> np.ndarray | None:
        """Frame ``i``'s plant region at the analysis size: the plant hull's points (or ``points``) projected and
        dilated by a voxel plus ``margin_cm`` (default: the ROI margin, half as wide again for a borrowed pose)."""
        import cv2

        points = ctx.hull_points if points is None else points
        if points is None or not ctx.roi_poses or ctx.roi_poses[i] is None:
            return None
        T = ctx.roi_poses[i]
        loose = ctx.poses[i] is None  # borrowed pose: a wider margin
        s = self.s
        if margin_cm is None:
            margin_cm = s.roi_margin_cm * (1.5 if loose else 1.0)
        h, w = self._smalls[i].shape
        uv, z = geo.project(points, T, self._Ks)
        ok = z > 1e-3
        u = np.round(uv[ok, 0]).astype(np.int64)
        v = np.round(uv[ok, 1]).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        roi = np.zeros((h, w), np.uint8)
        roi[v[inside], u[inside]] = 1
        depth = float(np.median(z[ok])) if ok.any() else 1.0
        r = (0.87 * ctx.voxel + margin_cm) * self._Ks[0, 0] / max(depth, 1e-3)
        return cv2.dilate(roi, _disk(np.ceil(r))).astype(bool)

    def _pot_mask(self, i: int, ctx: CaptureContext, W: int, H: int) -> np.ndarray:
        """Pixels of frame ``i`` where the (plant-coloured) pot is seen, not plant in front of it: bool ``[H, W]``."""
        import cv2

        T = ctx.roi_poses[i]
        sil = geo.pot_silhouette(ctx.pot, T, ctx.K, (W, H))
        if not sil.any():
            return sil
        # plant voxels nearer to the camera than the pot's axis (at their height) hide the pot
        pts = ctx.hull_points
        _, z = geo.project(pts, T, self._Ks)
        zc = np.clip(pts[:, 2], *ctx.pot["z"])
        axis = np.stack([np.full(len(pts), ctx.pot["axis"][0]), np.full(len(pts), ctx.pot["axis"][1]), zc], 1)
        _, za = geo.project(axis, T, self._Ks)
        front = pts[z < za]
        h, w = self._smalls[i].shape
        fr = np.zeros((h, w), np.uint8)
        if len(front):
            uv, zf = geo.project(front, T, self._Ks)
            u = np.round(uv[:, 0]).astype(np.int64)
            v = np.round(uv[:, 1]).astype(np.int64)
            ok = (zf > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            fr[v[ok], u[ok]] = 1
            r = 0.87 * ctx.voxel * self._Ks[0, 0] / max(float(np.median(zf)), 1e-3)
            fr = cv2.dilate(fr, _disk(np.ceil(r)))
        fr_full = cv2.resize(fr, (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)
        return sil & ~fr_full

    def _pot_hides_cube(self, i: int, ctx: CaptureContext, W: int, H: int) -> np.ndarray:
        """The pot's silhouette where the cube stands behind the pot in frame ``i`` (else nothing): bool ``[H, W]``."""
        T = ctx.roi_poses[i]
        cc = self.s.cube.corners().mean(axis=0, keepdims=True)  # [1, 3] cube centre
        axis = np.array([[ctx.pot["axis"][0], ctx.pot["axis"][1], float(np.mean(ctx.pot["z"]))]])
        _, zc = geo.project(cc, T, ctx.K)
        _, za = geo.project(axis, T, ctx.K)
        if zc[0] <= za[0]:
            return np.zeros((H, W), bool)
        return geo.pot_silhouette(ctx.pot, T, ctx.K, (W, H))

    def _roi_2d(self, i: int) -> np.ndarray:
        """Plant region without geometry: plant-coloured blobs nearest the image centre, joined."""
        import cv2

        small = self._smalls[i].astype(np.uint8)
        h, w = small.shape
        join = cv2.morphologyEx(small, cv2.MORPH_CLOSE, _disk(0.03 * max(h, w)))
        n, lab, stats, cents = cv2.connectedComponentsWithStats(join, connectivity=8)
        if n <= 1:
            return np.zeros((h, w), bool)
        areas = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
        d = np.hypot((cents[1:, 0] - w / 2) / w, (cents[1:, 1] - h / 2) / h)
        score = areas * np.exp(-((d / 0.3) ** 2))
        best = 1 + int(np.argmax(score))
        keep = lab == best
        grown = cv2.dilate(keep.astype(np.uint8), _disk(0.04 * max(h, w))).astype(bool)
        for k in range(1, n):
            if k != best and (grown & (lab == k)).any() and areas[k - 1] >= 0.002 * h * w:
                keep |= lab == k
        return cv2.dilate(keep.astype(np.uint8), _disk(0.02 * max(h, w))).astype(bool)

    def mask(self, i: int, rgb: np.ndarray, ctx: CaptureContext) -> tuple[np.ndarray, dict[str, Any]]:
        """Foreground (plant + cube) of frame ``i``: bool ``[H, W]`` and per-frame facts."""
        plant, cube, info = self.mask_parts(i, rgb, ctx)
        return plant | cube, info

    def _plant_in_box(self, rgb: np.ndarray, roi: np.ndarray, pot: np.ndarray | None, W: int, H: int,
                      fruit: np.ndarray | None = None, stems: np.ndarray | None = None) -> np.ndarray:
        """Plant mask of one frame's crop ``rgb`` ``[Hb, Wb, 3]`` around its plant region ``roi`` (bool, same size);
        ``pot``: where the plant-coloured pot is seen in the crop, or None; ``fruit``, ``stems``: where the fruit and
        stems seen in 3D project, or None; ``W``, ``H``: the whole frame's size, which sets every size threshold."""
        import cv2

        s = self.s
        Hb, Wb = rgb.shape[:2]
        strong, weak, pale, red_only = plant_colour_masks(rgb, s.colour, with_red=True)
        weak_any = weak  # before background colours are taken out
        fruit_colour = None
        if fruit is not None and fruit.any():
            # where the fruit hull projects, fruit colours are fruit even when the room shows them too: pieces of
            # fruit colour lying mostly there (a wall or box of that colour behind a fruit reaches far beyond it)
            fc = (red_only | (unripe_colour_mask(rgb, s.colour) if s.unripe_fruit_cm > 0 else False)).astype(np.uint8)
            n1, lab1, st1, _ = cv2.connectedComponentsWithStats(fc, connectivity=8)
            inside = np.bincount(lab1[fruit], minlength=n1)
            ok = inside >= s.fruit_inside * st1[:, cv2.CC_STAT_AREA]
            ok[0] = False
            fruit_colour = ok[lab1] & fruit
        if self._bg_learned:
            # background colours inside the plant region are left out where they form blobs (objects seen through
            # gaps, the pot); thin runs of them (petioles, peduncles, leaf edges against a similar wall) are kept
            q = _colour_bins(rgb)
            bg_colour = self._bg_ring[q]
            if pot is not None:
                bg_colour |= self._bg_pot[q] & pot  # not where plant hangs in front of it
            bgc = (bg_colour & (weak | pale)).astype(np.float32)
            k_thin = 2 * max(1, int(round(s.thin_px * max(H, W) / 960))) + 1
            keep = cv2.blur(bgc, (k_thin, k_thin)) < 0.5
            strong, weak, pale, red_only = strong & keep, weak & keep, pale & keep, red_only & keep
        if pot is not None and not self._bg_learned:
            roi = roi & ~pot
        # seeds: strong colour over a k x k neighbourhood (k = 2 px at 480, 3 px at 960): noisy pixels of green
        # walls seed nothing
        k = max(2, int(round(max(H, W) / 320)))
        seeds = cv2.morphologyEx(strong.astype(np.uint8), cv2.MORPH_OPEN, np.ones((k, k), np.uint8)).astype(bool) & roi
        band = cv2.dilate(seeds.astype(np.uint8), _disk(s.weak_band * max(H, W))).astype(bool)
        # hysteresis: weak components that contain a strong pixel; red ones only from strong red (fruit),
        # so that dark red/purple walls next to leaves are not grown into
        plant = np.zeros((Hb, Wb), bool)
        red_seeds = seeds & red_only
        # strong pixels join wherever they connect to a seed (thin petioles and peduncles, too narrow to seed)
        grow = band | strong
        for cand, sd in (((weak & ~red_only & roi & grow), seeds & ~red_only), ((red_only & roi & grow), red_seeds)):
            plant |= _components_with(cand, sd)
        # fruit- and flower-sized blobs of weak or pale colour touching the plant (unripe fruit, petals):
        # accepted whole, unlike large weak regions which only count within the band around strong seeds
        if plant.any():
            blob = (((weak & ~red_only) | pale) & roi & ~plant).astype(np.uint8)
            n2, lab2, st2, _ = cv2.connectedComponentsWithStats(blob, connectivity=8)
            if n2 > 1:
                touch = cv2.dilate(plant.astype(np.uint8), _disk(2)).astype(bool)
                ok = np.zeros(n2, bool)
                ok[np.unique(lab2[touch])] = True
                ok[0] = False
                ok &= st2[:, cv2.CC_STAT_AREA] <= s.pale_max_area * H * W
                plant |= ok[lab2]
        if fruit_colour is not None:
            plant |= fruit_colour
        if s.stem_px > 0 and self._bg_learned and plant.any():
            # thin runs attached to the plant: petioles and peduncles are olive to red-brown where they are not green,
            # and break the colour hysteresis above into pieces; what survives an opening of their width is a wide
            # region (soil, wood, a pot, a wall seen through a gap) and is left out, also where specks break it into
            # thin pieces (grit or perlite in the soil: closed by a pixel first). Only with the capture's learned
            # background colours, which keep out the grain of a brown floor or table next to the plant
            r = max(1, int(round(s.stem_px * max(H, W) / 960)))
            thin = _thin_runs((weak | stem_colour_mask(rgb, s.colour)) & ~bg_colour & roi & ~plant, r,
                              max(1, int(round(max(H, W) / 960))))
            plant |= _components_with(thin, cv2.dilate(plant.astype(np.uint8), _disk(2)).astype(bool))
        if stems is not None and stems.any() and plant.any():
            # where the stems seen in 3D project: thin runs that stand out from both flanks, touching the plant,
            # whatever the room's colours (an olive petiole against an olive wall)
            # only around where the stems project (the ridge filter is the costly part)
            reach = int(np.ceil(2 * max(_RIDGE_REACH) * max(H, W) / 960)) + 2
            ys, xs = np.nonzero(stems)
            y0, y1 = max(0, ys.min() - reach), min(Hb, ys.max() + 1 + reach)
            x0, x1 = max(0, xs.min() - reach), min(Wb, xs.max() + 1 + reach)
            thin = np.zeros_like(plant)
            thin[y0:y1, x0:x1] = self._stem_candidates(np.ascontiguousarray(rgb[y0:y1, x0:x1]), weak_any[y0:y1, x0:x1],
                                                       max(H, W) / 960, plant[y0:y1, x0:x1])
            thin &= stems & ~plant
            if pot is not None:
                thin &= ~pot
            # near the leaf it leaves, a stem's flank lands on the leaf and the run breaks off: touching = within the
            # flanks' farthest reach
            near = _disk(2 + max(_RIDGE_REACH) * max(H, W) / 960)
            plant |= _components_with(thin, cv2.dilate(plant.astype(np.uint8), near).astype(bool))
        # specks out, pinholes in
        n3, lab3, st3, _ = cv2.connectedComponentsWithStats(plant.astype(np.uint8), connectivity=8)
        if n3 > 1:
            big = st3[:, cv2.CC_STAT_AREA] >= s.min_blob * H * W
            big[0] = False
            plant = big[lab3]
        n4, lab4, st4, _ = cv2.connectedComponentsWithStats((~plant).astype(np.uint8), connectivity=4)
        if n4 > 1:
            x, y, w_, h_ = st4[:, 0], st4[:, 1], st4[:, 2], st4[:, 3]
            # touching the box's border: background (the margin around the region is never plant, and outside the
            # box there is none, so that is the same as touching the frame's border)
            border = (x == 0) | (y == 0) | (x + w_ >= Wb) | (y + h_ >= Hb)
            fill = (st4[:, cv2.CC_STAT_AREA] < s.fill_holes * H * W) & ~border
            fill[0] = False  # label 0 = the plant pixels themselves
            plant |= fill[lab4]
        if s.edge_radius > 0 and plant.any():
            # the mask's edges follow the image's: a guided filter of the mask with the frame's gray levels as the
            # guide, cut at one half, moves the outline onto the leaf edges (motion blur, video compression)
            r = max(1, int(round(s.edge_radius * max(H, W) / 960)))
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) * (1.0 / 255.0)
            plant = guided_filter(gray, plant.astype(np.float32), r, s.edge_eps) > 0.5
        return plant

    def mask_parts(self, i: int, rgb: np.ndarray, ctx: CaptureContext) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """Plant and cube masks of frame ``i`` separately: two bool ``[H, W]`` and per-frame facts."""
        import cv2

        s = self.s
        H, W = rgb.shape[:2]
        roi_small = self._roi_3d(i, ctx)
        locator = "3d" if ctx.poses and ctx.poses[i] is not None else "3d-interpolated"
        if roi_small is None:
            roi_small = self._roi_2d(i)
            locator = "2d"
        # the plant lies inside its region: everything below runs on the region's bounding box plus a margin
        # wider than any filter (same masks as on the whole frame; 2-3x fewer pixels)
        plant = np.zeros((H, W), bool)
        box = _crop_box(roi_small, W, H, max(16, int(round(_CROP_MARGIN * max(H, W) / 960))))
        if box is not None:
            x0, y0, x1, y1 = box
            roi = cv2.resize(roi_small.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)[y0:y1, x0:x1]
            pot = fruit = stems = None
            if ctx.pot is not None and locator != "2d":
                pot = self._pot_mask(i, ctx, W, H)[y0:y1, x0:x1]
            if ctx.fruit_points is not None and len(ctx.fruit_points) and locator != "2d":
                fr = self._roi_3d(i, ctx, ctx.fruit_points, 0.0)
                fruit = cv2.resize(fr.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)[y0:y1, x0:x1] > 0
            if ctx.stem_points is not None and len(ctx.stem_points) and locator != "2d":
                st = self._roi_3d(i, ctx, ctx.stem_points, 0.87 * max(ctx.stem_voxel - ctx.voxel, 0.0))
                stems = cv2.resize(st.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)[y0:y1, x0:x1] > 0
            plant[y0:y1, x0:x1] = self._plant_in_box(np.ascontiguousarray(rgb[y0:y1, x0:x1]), roi.astype(bool), pot, W, H,
                                                     fruit, stems)
        plant_fraction = float(plant.mean())
        cube = np.zeros((H, W), bool)
        pose = ctx.pose_source[i] if ctx.pose_source else "none"
        draw = ("markers", "features", "interpolated", "orbit") if s.cube_from_features else ("markers",)
        if s.use_cube and ctx.roi_poses and ctx.roi_poses[i] is not None and ctx.pose_source[i] in draw \
                and ctx.K is not None:
            cube = geo.cube_silhouette(ctx.roi_poses[i], ctx.K, ctx.dist, (W, H), s.cube)
            if s.cube_occlusion and cube.any():
                expected, faces = geo.cube_appearance(ctx.roi_poses[i], ctx.K, ctx.dist, (W, H), s.cube)
                if ctx.pose_source[i] != "markers":  # a borrowed camera: move the drawn cube onto the frame's
                    moved = geo.align_cube(rgb, expected, faces)
                    if moved is not None:
                        expected, faces, _ = moved
                    # and only the faces whose print the frame shows (a pot of any colour may hide the cube)
                    faces = geo.faces_shown(rgb, expected, faces)
                    cube = faces >= 0
                hidden = geo.cube_occluded(rgb, expected, faces)
                cube &= ~(hidden | (faces < 0))
            if ctx.pot is not None and cube.any():
                cube &= ~self._pot_hides_cube(i, ctx, W, H)
        fg = plant | cube
        return plant, cube, {"plant_fraction": plant_fraction, "cube_fraction": float(cube.mean()),
                    "foreground_fraction": float(fg.mean()), "locator": locator, "cube_pose": pose,
                    "markers": sorted(ctx.detections[i])}

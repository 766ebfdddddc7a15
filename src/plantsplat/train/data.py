"""Training data from a workspace: cameras (COLMAP model or transforms.json), undistorted images and
masks, the train/test split, and initial points.

Cameras are pinhole after loading: images and masks of distorted cameras (OPENCV, SIMPLE_RADIAL,
...) are undistorted with OpenCV onto the same intrinsics. Poses are world->camera in OpenCV axes
(x right, y down, z forward), in the workspace's calibrated frame (cm, z up).

Usage:
    from plantsplat.workspace import Workspace
    scene = load_scene(Workspace("ws/plant_01"), need_masks=True)
    scene.views[0].image.shape
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.ply import read_point_cloud
from plantsplat.pycolmap_loader import load_pycolmap
from plantsplat.resources import map_on_cores
from plantsplat.workspace import Workspace

log = get_logger(__name__)

# COLMAP camera model -> (fx, fy, cx, cy, cv2 distortion) from its params
_MODELS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], []),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], []),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], 0, 0, 0]),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], p[4], 0, 0]),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], list(p[4:8])),
    "FULL_OPENCV": lambda p: (p[0], p[1], p[2], p[3], list(p[4:12])),
}


@dataclass
class View:
    """One calibrated frame (pinhole after undistortion)."""

    name: str
    K: np.ndarray  # [3, 3] pinhole intrinsics at full resolution
    viewmat: np.ndarray  # [4, 4] world -> camera, OpenCV axes
    width: int
    height: int
    image: np.ndarray | None = None  # [H, W, 3] uint8, undistorted
    mask: np.ndarray | None = None  # [H, W] uint8 (255 = foreground), undistorted
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # cv2 distortion still to undo (none once loaded)
    frame_dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # the frame's own lens distortion (cv2 order)
    raw: np.ndarray | None = None  # [H, W, 3] uint8, the frame as decoded (load_scene's keep_raw)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``[3]``."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t


@dataclass
class Scene:
    views: list[View]
    points: np.ndarray  # [P, 3] SfM points (may be empty)
    colors: np.ndarray  # [P, 3] uint8
    pose_source: str


def _cameras_from_colmap(path: Path) -> tuple[dict[str, View], np.ndarray, np.ndarray]:
    pycolmap = load_pycolmap()  # only where a COLMAP model is read, with the CLI's SIGTERM handler kept

    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:
        raise PlantsplatError(f"{path}: unreadable COLMAP model ({exc}); re-run `plantsplat poses`") from exc
    views = {}
    for im in rec.images.values():
        if hasattr(im, "has_pose") and not im.has_pose:
            continue
        cam = rec.cameras[im.camera_id]
        model = str(cam.model).split(".")[-1]
        if model not in _MODELS:
            raise PlantsplatError(
                f"{path}: camera model {model} is not supported; use PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV"
            )
        fx, fy, cx, cy, dist = _MODELS[model](list(cam.params))
        vm = np.eye(4)
        vm[:3, :4] = im.cam_from_world().matrix()
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        views[Path(im.name).name] = View(Path(im.name).name, K, vm, int(cam.width), int(cam.height),
                                         dist=np.asarray(dist, dtype=np.float64))
    pts = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    cols = np.array([p.color for p in rec.points3D.values()], dtype=np.uint8).reshape(-1, 3)
    return views, pts, cols


def _cameras_from_transforms(path: Path) -> dict[str, View]:
    data = read_json(path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise PlantsplatError(f"{path}: no 'frames' list; re-run `plantsplat poses`")
    views = {}
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL camera axes -> OpenCV
    for fr in frames:
        get = lambda k, d=None: fr.get(k, data.get(k, d))  # noqa: E731  per-frame overrides global
        try:
            fx, fy, cx, cy = float(get("fl_x")), float(get("fl_y", get("fl_x"))), float(get("cx")), float(get("cy"))
            w, h = int(get("w")), int(get("h"))
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, KeyError, ValueError) as exc:
            raise PlantsplatError(f"{path}: frame {fr.get('file_path')} lacks intrinsics or a pose ({exc})") from exc
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        dist = [float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
        name = Path(fr["file_path"]).name
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        views[name] = View(name, K, np.linalg.inv(c2w @ flip), w, h, dist=np.asarray(dist))
    return views


def sparse_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """x, y, z [N, 3] and colours [N, 3] uint8 (grey where the PLY has none) of a point-cloud PLY."""
    cloud = read_point_cloud(path, "re-run `plantsplat poses`")
    cols = cloud["rgb"] if cloud["rgb"] is not None else np.full((len(cloud["xyz"]), 3), 128, np.uint8)
    return cloud["xyz"], cols


def _undistort(img: np.ndarray, view: View, nearest: bool) -> np.ndarray:
    if view.dist.size == 0 or not np.any(np.abs(view.dist) > 0):
        return img
    m1, m2 = cv2.initUndistortRectifyMap(view.K, view.dist, None, view.K, (view.width, view.height), cv2.CV_32FC1)
    return cv2.remap(img, m1, m2, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _load_frame(ws: Workspace, name: str, v: View, source: str, need_masks: bool, keep_raw: bool = False) -> View:
    """Frame ``name``'s image and, when it has one, its mask, undistorted into its camera ``v``; returns ``v``.
    ``keep_raw``: the frame as decoded stays in ``v.raw`` too (the same array where nothing is undistorted)."""
    img = read_image(ws.images_dir / name, "rgb")
    if img.shape[:2] != (v.height, v.width):
        raise PlantsplatError(
            f"{ws.images_dir / name}: {img.shape[1]}x{img.shape[0]} but its camera in {source} is "
            f"{v.width}x{v.height}; re-run `plantsplat poses {ws.root}`"
        )
    v.image = _undistort(img, v, nearest=False)
    v.raw = img if keep_raw else None
    mpath = ws.masks_dir / name
    if mpath.is_file():
        m = read_image(mpath, "gray")
        if m.shape != img.shape[:2]:
            raise PlantsplatError(
                f"{mpath}: {m.shape[1]}x{m.shape[0]} but the frame is {img.shape[1]}x{img.shape[0]}; "
                f"re-run `plantsplat segment {ws.root}`"
            )
        v.mask = _undistort(m, v, nearest=True)
    elif need_masks:
        raise PlantsplatError(
            f"{mpath}: missing mask (object mode needs one per frame); run `plantsplat segment {ws.root}` "
            "or train with --mode full"
        )
    return v


def excluded_frames(ws: Workspace) -> dict[str, str]:
    """Frames the segment stage found no plant in (``segment.json``'s ``excluded``): ``{name: reason}``."""
    if not ws.segment_json.is_file():
        return {}
    return {e["name"]: e.get("reason", "") for e in read_json(ws.segment_json).get("excluded", [])}


def training_scene(ws: Workspace, mode: str, keep_raw: bool = False) -> Scene:
    """The frames a model of ``mode`` ("object" or "full") trains on. An object model leaves out the frames the segment
    stage found no plant in; a whole-scene model keeps every posed frame: the segment stage's quick model is one, and
    trains before ``segment.json`` is rewritten, so it must not depend on an earlier run's masks (a forced re-run of
    the segment stage trains the same quick model as its first run)."""
    return load_scene(ws, need_masks=mode == "object", skip_excluded=mode == "object", keep_raw=keep_raw)


def load_scene(ws: Workspace, need_masks: bool, load_images: bool = True, skip_excluded: bool = False,
               keep_raw: bool = False) -> Scene:
    """Cameras, undistorted images and masks, and SfM points of a workspace.

    Poses come from ``sparse/0`` when present, else ``transforms.json``. Frames without a pose are
    skipped with a warning; a mask that is missing or of another size is an error when
    ``need_masks`` (object mode), else masks are loaded when present (for PBR evaluation).
    ``skip_excluded``: leave out the frames in which the segment stage found no plant. ``keep_raw``: each
    view keeps its frame as decoded too (``View.raw``), for a caller that needs it after training.
    """
    ws.require(ws.images_dir, "frames")
    names = ws.image_names()
    if skip_excluded:
        excluded = excluded_frames(ws)
        if excluded:
            log.info("%d frame(s) without a plant are left out (%s)", len(excluded), ", ".join(sorted(excluded)[:5]))
        names = [n for n in names if n not in excluded]
    if not names:
        raise PlantsplatError(f"{ws.images_dir}: no images; run `plantsplat frames` first")
    if ws.sparse_dir.is_dir() and any(ws.sparse_dir.iterdir()):
        cams, pts, cols = _cameras_from_colmap(ws.sparse_dir)
        source = str(ws.sparse_dir)
    elif ws.transforms_json.is_file():
        cams = _cameras_from_transforms(ws.transforms_json)
        pts, cols = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        source = str(ws.transforms_json)
    else:
        raise PlantsplatError(f"{ws.root}: no camera poses (sparse/0 or transforms.json); run `plantsplat poses {ws.root}` first")
    if len(pts) == 0 and ws.sparse_points_ply.is_file():
        pts, cols = sparse_points(ws.sparse_points_ply)

    posed = [n for n in names if n in cams]
    unposed = [n for n in names if n not in cams]
    if unposed:
        log.warning("%d of %d frames have no pose in %s and are skipped (e.g. %s)", len(unposed), len(names), source, unposed[0])
    if len(posed) < 2:
        raise PlantsplatError(
            f"{source}: only {len(posed)} of the frames in {ws.images_dir} have a pose; the poses do not match "
            f"the images; re-run `plantsplat poses {ws.root}`"
        )
    if load_images:  # on every core: decoding and undistorting release the GIL; in frame order either way
        views = list(map_on_cores(lambda n: _load_frame(ws, n, cams[n], source, need_masks, keep_raw), posed,
                                  "loading frames"))
    else:
        views = [cams[n] for n in posed]
    for v in views:  # pinhole from here on; the frames' own lens is kept to place a render back onto a frame
        v.frame_dist, v.dist = v.dist, np.zeros(0)
    return Scene(views, np.asarray(pts, np.float64).reshape(-1, 3), np.asarray(cols, np.uint8).reshape(-1, 3), source)


# ---------------------------------------------------------------------------------------------
# split


def make_split(names: list[str], test_fraction: float = 0.4, test_every: int = 0) -> dict:
    """Train/test split of sorted frame names.

    ``test_every=k`` holds out every k-th frame (0, k, 2k, ...); otherwise ``1 - test_fraction`` of
    the frames, evenly spaced (as nerfstudio), are training frames and the rest are test frames.

    Example:
        >>> make_split([f"f{i}" for i in range(5)], 0.4)["test"]
        ['f1', 'f3']
    """
    n = len(names)
    if test_every and test_every > 0:
        test_idx = set(range(0, n, test_every))
        method = f"every {test_every}th frame held out"
    else:
        n_train = max(1, int(math.ceil(n * (1.0 - test_fraction))))
        train_idx = set(np.linspace(0, n - 1, n_train).round().astype(int).tolist())
        test_idx = set(range(n)) - train_idx
        method = f"{round(100 * (1 - test_fraction))}/{round(100 * test_fraction)} evenly spaced"
    train = [names[i] for i in range(n) if i not in test_idx]
    test = [names[i] for i in range(n) if i in test_idx]
    if not train:
        raise PlantsplatError(f"--test-every {test_every} leaves no training frames; use a larger value")
    return {"method": method, "train": train, "test": test}


def load_or_make_split(path: Path, names: list[str], test_fraction: float, test_every: int) -> dict:
    """Reuse ``train/split.json`` when it matches the frames, so evaluation sees the same test views."""
    if path.is_file():
        split = read_json(path)
        known = set(split.get("train", [])) | set(split.get("test", []))
        if known and known <= set(names):
            return split
        raise PlantsplatError(
            f"{path}: the stored split names frames that are no longer in the workspace; delete {path.parent} "
            "to train from scratch"
        )
    split = make_split(names, test_fraction, test_every)
    write_json_atomic(path, split)
    return split


# ---------------------------------------------------------------------------------------------
# initial points


def project(points: np.ndarray, view: View) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[P, 2]`` and depths ``[P]`` of world points in a view."""
    cam = points @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]  # [P, 3]
    z = cam[:, 2]
    uv = cam[:, :2] / np.maximum(z[:, None], 1e-9) * np.array([view.K[0, 0], view.K[1, 1]]) + view.K[:2, 2]
    return uv, z


def pixels_hit(points: np.ndarray, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which world points ``[P, 3]`` fall inside the view's image, in front of it, and the pixel each falls in:
    ``(inside [P] bool, column [P], row [P])`` (column and row are meaningful where inside)."""
    uv, z = project(points, view)
    # behind the camera, or so far off the image that the integer cast would overflow: outside
    uv = np.clip(np.where((z > 0)[:, None], np.nan_to_num(uv, nan=-1.0), -1.0), -1.0, max(view.width, view.height))
    u = np.floor(uv[:, 0]).astype(np.int64)
    w = np.floor(uv[:, 1]).astype(np.int64)
    return (u >= 0) & (w >= 0) & (u < view.width) & (w < view.height), u, w


def mask_votes(points: np.ndarray, views: list[View]) -> tuple[np.ndarray, np.ndarray]:
    """For each point: in how many views it projects inside the image, and inside the mask."""
    seen = np.zeros(len(points), np.int32)
    inside = np.zeros(len(points), np.int32)
    for v in views:
        if v.mask is None:
            continue
        ok, u, w = pixels_hit(points, v)
        seen += ok
        hit = np.zeros(len(points), bool)
        hit[ok] = v.mask[w[ok], u[ok]] > 127
        inside += hit
    return seen, inside


def masked_points(points: np.ndarray, views: list[View]) -> tuple[np.ndarray, np.ndarray]:
    """Which points ``[P, 3]`` belong to the masked object: inside the masks of at least half of the
    views that see them, and of at least 2. Returns that bool ``[P]`` and the number of views that see
    each point ``[P]``."""
    seen, inside = mask_votes(points, views)
    return (inside >= 2) & (inside >= 0.5 * np.maximum(seen, 1)), seen


def scene_center_radius(views: list[View]) -> tuple[np.ndarray, float]:
    """The point nearest to all optical axes (least squares) and the median camera distance to it."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for v in views:
        d = v.viewmat[2, :3]  # optical axis in world (third row of R)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ v.center
    center = np.linalg.lstsq(A, b, rcond=None)[0]
    radius = float(np.median([np.linalg.norm(v.center - center) for v in views]))
    return center, radius


def visual_hull_points(views: list[View], center: np.ndarray, radius: float, n: int, rng: np.random.Generator,
                       dilate_frac: float = 0.01, rounds: int = 30, min_inside: float = 0.8) -> np.ndarray:
    """Up to ``n`` random points ``[M, 3]`` inside the masks' visual hull.

    Candidates are drawn on the rays of random mask pixels of random views, at depths within
    ``radius`` of ``center``, and kept when they fall inside the (slightly dilated) masks of at least
    ``min_inside`` of the views that see them; this finds thin structures (stems) that uniform
    sampling of a box misses. Not every view: the pot, which is not in the masks, hides the cube and
    hanging fruit from some views, and a strict hull dropped them (the cube was then never
    reconstructed: foreground PSNR 10.9 dB against 18.5 dB with 0.8, 600 steps on a synthetic capture
    with true cameras).
    """
    masked = [v for v in views if v.mask is not None and (v.mask > 127).any()]
    if not masked:
        return np.zeros((0, 3))
    dil = []
    for v in masked:
        k = max(1, int(dilate_frac * max(v.width, v.height))) * 2 + 1
        dil.append(View(v.name, v.K, v.viewmat, v.width, v.height,
                        mask=cv2.dilate(v.mask, np.ones((k, k), np.uint8))))
    found, total = [], 0
    per_round = max(4 * n // max(1, len(masked)), 2000)
    for _ in range(rounds):
        for v in masked:
            ys, xs = np.nonzero(v.mask > 127)
            pick = rng.integers(0, len(xs), size=per_round)
            pix = np.stack([xs[pick] + rng.random(per_round), ys[pick] + rng.random(per_round)], -1)  # [P, 2]
            rays = np.concatenate([(pix - v.K[:2, 2]) / np.array([v.K[0, 0], v.K[1, 1]]), np.ones((per_round, 1))], -1)
            dist = np.linalg.norm(v.center - center)
            z = rng.uniform(max(1e-3, dist - radius), dist + radius, size=(per_round, 1))
            cam = rays * z  # [P, 3] camera coordinates
            R, t = v.viewmat[:3, :3], v.viewmat[:3, 3]
            world = (cam - t) @ R  # [P, 3]
            seen, inside = mask_votes(world, dil)
            # seen by most views (cameras circle the object) and inside most masks that see it
            keep = (seen >= max(2, int(0.6 * len(dil)))) & (inside >= min_inside * seen)
            found.append(world[keep])
            total += int(keep.sum())
        if total >= n:
            break
    pts = np.concatenate(found) if found else np.zeros((0, 3))
    return pts[rng.permutation(len(pts))[:n]]


def initial_points(scene: Scene, views: list[View], object_mode: bool, n_random: int, rng: np.random.Generator,
                   min_points: int = 200) -> tuple[np.ndarray, np.ndarray, str]:
    """Initial Gaussian centres ``[N, 3]`` and colours ``[N, 3]`` in [0, 1].

    SfM points first; in object mode only those inside the masks in at least half of the views that
    see them (and at least 2). With too few points: random points inside the foreground's bounds
    (object mode: the masks' visual hull inside the cameras' common look-at region; full mode: a
    sphere around it).
    """
    pts, cols = scene.points, scene.colors.astype(np.float64) / 255.0
    how = "sfm"
    if len(pts) and object_mode:
        keep, _ = masked_points(pts, views)
        pts, cols = pts[keep], cols[keep]
        how = "sfm (inside masks)"
    if len(pts) >= min_points:
        return pts, cols, how
    center, radius = scene_center_radius(views)
    if object_mode:
        hull = visual_hull_points(views, center, radius, n_random, rng)
        if len(hull) < 50:
            raise PlantsplatError(
                "the masks and camera poses do not agree on any 3D region (empty visual hull); check the masks "
                "(`masks_preview.png`) and the poses (`poses.json`)"
            )
        return hull, mean_colors(hull, views), "random (mask visual hull)"
    d = rng.normal(size=(n_random, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = radius * 1.5 * rng.uniform(0, 1, size=(n_random, 1)) ** (1 / 3)
    pts = center + d * r
    return pts, mean_colors(pts, views), "random (sphere around the cameras' target)"


def occluder_points(scene: Scene, views: list[View], margin: float = 0.3) -> np.ndarray:
    """SfM points ``[M, 3]`` that the masks leave out near the object: the pot, the soil, the table.

    Object mode renders only what the masks hold, but the masks also leave out what an unmasked
    object in front hides (the pot hides the cube and hanging fruit from some views). These points,
    inside the bounding box of the points the masks keep (widened by ``margin`` of its size on every
    side), seed occluders: Gaussians drawn in the background colour, which hide what lies behind them
    and are never exported. Empty without SfM points.
    """
    pts = scene.points
    if len(pts) == 0:
        return np.zeros((0, 3))
    kept, seen = masked_points(pts, views)
    if kept.sum() < 10:
        return np.zeros((0, 3))
    lo, hi = pts[kept].min(0), pts[kept].max(0)
    pad = margin * (hi - lo)
    near = np.all((pts >= lo - pad) & (pts <= hi + pad), axis=1)
    return pts[near & ~kept & (seen >= 2)]


def mean_colors(points: np.ndarray, views: list[View]) -> np.ndarray:
    """Mean image colour ``[P, 3]`` in [0, 1] of each point over the views it projects into (no
    occlusion test: a starting value that saves the optimiser many steps); grey where unseen."""
    acc = np.zeros((len(points), 3))
    cnt = np.zeros(len(points))
    for v in views:
        if v.image is None:
            continue
        ok, u, w = pixels_hit(points, v)
        acc[ok] += v.image[w[ok], u[ok]] / 255.0
        cnt[ok] += 1
    out = np.full((len(points), 3), 0.5)
    seen = cnt > 0
    out[seen] = acc[seen] / cnt[seen, None]
    return out

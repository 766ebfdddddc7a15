"""Structure from motion with pycolmap: SIFT features, matching, incremental or global mapping.

Everything runs on the CPU through pycolmap (COLMAP 3.x/4.x bindings). COLMAP's own defaults are
tuned for unordered photo collections; for a video circling a plant they split the model or
register a wrong fragment (see issue 4), so :class:`SfmOptions` sets its own defaults: one shared
camera with a phone-style radial distortion model, a capped number of SIFT features (enough for
540x960 frames, and it makes exhaustive matching affordable), exhaustive matching for up to
``exhaustive_max_frames`` frames and sequential matching with a wide quadratic window above.

Example:
    >>> from plantsplat.poses.sfm import SfmOptions, run_sfm
    >>> res = run_sfm("ws/images", ["frame_00000.png", ...], "ws/colmap", SfmOptions())  # doctest: +SKIP
    >>> res.models[0].num_reg_images()  # doctest: +SKIP
    120
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.log import get_logger

log = get_logger(__name__)

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class SfmOptions:
    """Options of the SfM run (a subset of COLMAP's, with defaults suited to plant videos)."""

    camera_model: str = "RADIAL"
    """COLMAP camera model shared by all frames (phones: RADIAL = f, cx, cy, k1, k2)."""
    matcher: str = "auto"
    """'guided' (video neighbours + frames that see the cube from similar directions), 'exhaustive',
    'sequential', or 'auto' (guided when most frames see the cube, else exhaustive up to
    exhaustive_max_frames frames, else sequential)."""
    mapper: str = "auto"
    """'incremental', 'global', or 'auto' (incremental, global when it registers more frames)."""
    max_features: int = 4096
    """SIFT features kept per frame."""
    peak_threshold: float = 0.004
    """SIFT peak threshold (COLMAP: 0.0067); lower finds more features on plain walls and small frames."""
    first_octave: int = -1
    """SIFT first octave: -1 (COLMAP's default) upsamples the frame 2x to find small features; 0 is faster."""
    max_image_size: int = 1600
    """Longest side used for feature extraction (pixels); larger frames are downscaled."""
    exhaustive_max_frames: int = 80
    """With matcher 'auto', frame count above which sequential matching is used."""
    sequential_overlap: int = 20
    """Sequential matching: neighbours matched on each side (plus quadratic steps beyond)."""
    guided_window: int = 5
    """Guided matching: video neighbours matched on each side (plus quadratic steps beyond)."""
    guided_neighbours: int = 20
    """Guided matching: frames matched per frame by closest viewing direction of the cube."""
    guided_max_angle_deg: float = 45.0
    """Guided matching: largest angle between two frames' directions from the cube."""
    ransac_max_trials: int = 2000
    """Two-view geometric verification: RANSAC trials per pair (COLMAP: 10000)."""
    num_threads: int = 2
    """CPU threads for extraction, matching and mapping."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mapper (repeatable runs)."""
    verbose: bool = False
    """Show COLMAP's own log on stderr."""


@dataclass
class SfmResult:
    models: list  # [pycolmap.Reconstruction], largest first
    database: Path
    matcher: str
    mapper: str
    timings: dict = field(default_factory=dict)


@contextlib.contextmanager
def colmap_logging(verbose: bool):
    """Silence COLMAP's output on stderr unless ``verbose`` (restored afterwards).

    glog's level is raised to errors, and file descriptor 2 is sent to /dev/null for the duration
    because some pycolmap calls (bundle adjustment) print their reports regardless of the level.
    Do not log from inside this block: it would be swallowed too.
    """
    import sys

    import pycolmap

    if verbose:
        yield
        return
    old = pycolmap.logging.minloglevel
    old_v = pycolmap.logging.verbose_level
    pycolmap.logging.minloglevel = 2  # errors only
    pycolmap.logging.verbose_level = 0
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)
        pycolmap.logging.minloglevel = old
        pycolmap.logging.verbose_level = old_v


def choose_matcher(opts: SfmOptions, n: int, n_cube_poses: int = 0) -> str:
    if opts.matcher == "auto":
        if n_cube_poses >= 0.5 * n and n > 2 * opts.guided_window + 2:
            return "guided"
        return "exhaustive" if n <= opts.exhaustive_max_frames else "sequential"
    if opts.matcher not in ("guided", "exhaustive", "sequential"):
        raise PlantsplatError(f"--matcher {opts.matcher!r}: use guided, exhaustive, sequential or auto", exit_code=2)
    return opts.matcher


def view_directions(
    detections: dict[str, dict[int, np.ndarray]], image_size: tuple[int, int], cube
) -> dict[str, np.ndarray]:
    """Unit direction from the cube to the camera (cube frame) for every frame whose markers give a pose.

    The intrinsics are not known yet: a focal length of the image's longest side is assumed, which
    changes the distance far more than the direction.
    """
    from plantsplat.cube import cube_pose

    w, h = image_size
    f = float(max(w, h))
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    out = {}
    for name, det in detections.items():
        res = cube_pose(det, K, None, cube)
        if res is None:
            continue
        T = res[0]  # cam_from_cube
        c = -T[:3, :3].T @ T[:3, 3]  # camera centre in the cube frame
        c = c - np.array([0.0, 0.0, cube.size / 2])
        if np.linalg.norm(c) > 0:
            out[name] = c / np.linalg.norm(c)
    return out


def guided_pairs(names: list[str], directions: dict[str, np.ndarray], opts: SfmOptions) -> list[tuple[str, str]]:
    """Image pairs to match: video neighbours (window + quadratic steps) and cube-guided neighbours.

    Each frame with a cube direction is paired with up to ``guided_neighbours`` frames whose
    direction from the cube is within ``guided_max_angle_deg``, which links the rings of an orbit
    capture and closes its loops without matching every pair.
    """
    n = len(names)
    pairs: set[tuple[int, int]] = set()
    steps = set(range(1, opts.guided_window + 1))
    k = 1
    while 2**k < n:
        steps.add(2**k + opts.guided_window - 1)
        k += 1
    for i in range(n):
        # frames that do not see the cube only have their video neighbours: give them a wider window
        wide = names[i] not in directions or (i + 1 < n and names[i + 1] not in directions)
        for d in steps | (set(range(1, 2 * opts.guided_window + 1)) if wide else set()):
            if i + d < n:
                pairs.add((i, i + d))
    idx = [i for i, nm in enumerate(names) if nm in directions]
    if len(idx) > 1:
        D = np.array([directions[names[i]] for i in idx])  # [M, 3]
        cos = np.clip(D @ D.T, -1.0, 1.0)  # [M, M]
        np.fill_diagonal(cos, -2.0)
        cmin = np.cos(np.radians(opts.guided_max_angle_deg))
        for a, i in enumerate(idx):
            order = np.argsort(-cos[a])[: opts.guided_neighbours]
            for b in order:
                if cos[a, b] >= cmin:
                    j = idx[b]
                    pairs.add((min(i, j), max(i, j)))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


def extract_and_match(
    image_dir: Path,
    names: list[str],
    work_dir: Path,
    opts: SfmOptions,
    directions: dict[str, np.ndarray] | None = None,
) -> tuple[Path, str, dict]:
    """Extract SIFT features and match them into ``work_dir/database.db`` (rebuilt from scratch).

    ``directions`` (from :func:`view_directions`) enables guided matching. Returns
    ``(database path, matcher used, timings)``; timings include ``pairs``, the number of pairs matched.
    """
    import pycolmap

    if opts.camera_model not in CAMERA_MODELS:
        raise PlantsplatError(f"--camera-model {opts.camera_model!r}: use one of {', '.join(CAMERA_MODELS)}", exit_code=2)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    for p in (db, work_dir / "database.db-wal", work_dir / "database.db-shm"):
        p.unlink(missing_ok=True)
    timings: dict[str, float] = {}
    device = pycolmap.Device.cpu
    pycolmap.set_random_seed(opts.seed)
    t = time.perf_counter()
    log.info("SfM: extracting SIFT features from %d frames", len(names))
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts.num_threads
    ext.max_image_size = opts.max_image_size
    ext.sift.max_num_features = opts.max_features
    ext.sift.peak_threshold = opts.peak_threshold
    ext.sift.first_octave = opts.first_octave
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    with colmap_logging(opts.verbose):
        pycolmap.extract_features(
            db,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=ext,
            device=device,
        )
    timings["extract_s"] = time.perf_counter() - t

    directions = directions or {}
    matcher = choose_matcher(opts, len(names), len(directions))
    t = time.perf_counter()
    mopts, verif = _matching_options(opts)
    n = len(names)
    if matcher == "guided":
        pairs = guided_pairs(names, directions, opts)
        timings["pairs"] = len(pairs)
        pair_file = work_dir / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    elif matcher == "exhaustive":
        timings["pairs"] = n * (n - 1) // 2
    log.info("SfM: %s matching%s", matcher, f" ({timings['pairs']} pairs)" if "pairs" in timings else "")
    with colmap_logging(opts.verbose):
        if matcher == "guided":
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(
                db, matching_options=mopts, pairing_options=pairing, verification_options=verif, device=device
            )
        elif matcher == "exhaustive":
            pycolmap.match_exhaustive(db, matching_options=mopts, verification_options=verif, device=device)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = opts.sequential_overlap
            pairing.quadratic_overlap = True
            pairing.loop_detection = False  # needs a vocabulary tree download
            pycolmap.match_sequential(
                db, matching_options=mopts, pairing_options=pairing, verification_options=verif, device=device
            )
    timings["match_s"] = time.perf_counter() - t
    return db, matcher, timings


def incremental(db: Path, image_dir: Path, out_dir: Path, opts: SfmOptions, input_path: Path | None = None) -> list:
    """COLMAP incremental mapping; returns the models found, largest first."""
    import pycolmap

    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = opts.num_threads
    o.random_seed = opts.seed
    o.mapper.random_seed = opts.seed
    o.triangulation.random_seed = opts.seed
    o.min_model_size = 3
    # orbits around a small object: neighbouring frames are close, initial pairs need less parallax
    o.mapper.init_min_tri_angle = 8.0
    with colmap_logging(opts.verbose):
        models = pycolmap.incremental_mapping(
            db, image_dir, out_dir, options=o, input_path=str(input_path) if input_path else ""
        )
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


def global_sfm(db: Path, image_dir: Path, out_dir: Path, opts: SfmOptions) -> list:
    """GLOMAP-style global mapping (rotation averaging + global positioning + BA); largest first."""
    import pycolmap

    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    o = pycolmap.GlobalPipelineOptions()
    o.num_threads = opts.num_threads
    o.random_seed = opts.seed
    o.mapper.num_threads = opts.num_threads
    o.mapper.random_seed = opts.seed
    o.mapper.global_positioning.use_gpu = False
    o.mapper.bundle_adjustment.ceres.use_gpu = False
    with colmap_logging(opts.verbose):
        models = pycolmap.global_mapping(db, image_dir, out_dir, options=o)
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


def refine(rec, db: Path, image_dir: Path, work_dir: Path, opts: SfmOptions, retriangulate: bool = True,
           adjust: bool = True):
    """Re-triangulate all matches with the current poses, then a full bundle adjustment.

    With ``adjust=False`` the poses and intrinsics are kept as they are: only the points are
    triangulated (and refined). Returns the refined reconstruction (a new object when re-triangulated).
    """
    import pycolmap

    with colmap_logging(opts.verbose):
        if retriangulate:
            out = work_dir / "retriangulated"
            if out.exists():
                shutil.rmtree(out)
            out.mkdir(parents=True)
            o = pycolmap.IncrementalPipelineOptions()
            o.num_threads = opts.num_threads
            o.random_seed = opts.seed
            rec = pycolmap.triangulate_points(rec, db, image_dir, out, clear_points=True, options=o, refine_intrinsics=adjust)
        if not adjust:
            return rec
        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = True
        ba.refine_extra_params = True
        ba.refine_principal_point = False
        ba.ceres.use_gpu = False
        ba.ceres.solver_options.num_threads = opts.num_threads
        ba.ceres.solver_options.max_num_iterations = 100
        ba.print_summary = False
        pycolmap.bundle_adjustment(rec, ba)
    return rec


def n_threads_env(n: int) -> None:
    """Cap OpenMP/BLAS threads used inside COLMAP's dependencies."""
    os.environ.setdefault("OMP_NUM_THREADS", str(n))


def _matching_options(opts: SfmOptions):
    """pycolmap's matching and two-view verification options for ``opts`` (threads, seeded RANSAC)."""
    import pycolmap

    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = opts.num_threads
    verif = pycolmap.TwoViewGeometryOptions()
    verif.ransac.random_seed = opts.seed
    verif.ransac.max_num_trials = opts.ransac_max_trials
    verif.detect_watermark = False
    return mopts, verif


def match_pairs(db: Path, work_dir: Path, pairs: list[tuple[str, str]], opts: SfmOptions, tag: str) -> None:
    """Match and verify extra image ``pairs`` into ``db`` (pairs matched before are skipped by COLMAP)."""
    import pycolmap

    pair_file = work_dir / f"pairs_{tag}.txt"
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    mopts, verif = _matching_options(opts)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_file)
    with colmap_logging(opts.verbose):
        pycolmap.match_image_pairs(
            db, matching_options=mopts, pairing_options=pairing, verification_options=verif, device=pycolmap.Device.cpu
        )


def pairs_for_missing(names: list[str], rec, k: int = 12, window: int = 3) -> list[tuple[str, str]]:
    """Pairs linking each unregistered frame to registered frames near its registered video neighbours.

    For a missing frame, the registered frames closest in video order (up to ``window`` on each
    side) stand in for its unknown position; the ``k`` registered cameras nearest to each of them
    (camera centres in the model) are paired with it.
    """
    reg = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    reg_names = [n for n in names if n in reg]
    if not reg_names:
        return []
    C = np.array([reg[n] for n in reg_names])  # [R, 3]
    order = {n: i for i, n in enumerate(names)}
    pairs = set()
    for i, n in enumerate(names):
        if n in reg:
            continue
        before = [m for m in names[max(0, i - 4 * window) : i] if m in reg][-window:]
        after = [m for m in names[i + 1 : i + 1 + 4 * window] if m in reg][:window]
        for m in before + after:
            d = np.linalg.norm(C - reg[m], axis=1)
            for j in np.argsort(d)[:k]:
                a, b = sorted((n, reg_names[j]), key=order.get)
                pairs.add((a, b))
        for m in names[max(0, i - 2 * window) : i + 2 * window + 1]:  # its video neighbours, registered or not
            if m != n:
                a, b = sorted((n, m), key=order.get)
                pairs.add((a, b))
    return sorted(pairs, key=lambda p: (order[p[0]], order[p[1]]))

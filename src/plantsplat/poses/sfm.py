"""Structure from motion with pycolmap: SIFT features, matching of chosen pairs, incremental or global mapping.

Everything runs on the CPU through pycolmap. Whole frames are used (the room's texture is what SfM
lives on) and neither masks nor the cube are needed: which frames to match is chosen by
:mod:`plantsplat.poses.pairs` (video neighbours and visually similar frames), then COLMAP's
incremental mapper registers them.

Usage:
    opts = PosesConfig().sfm_options()
    db = extract_features(Path("ws/images"), names, Path("ws/.plantsplat/colmap"), opts)
    match_pairs(db, Path("ws/.plantsplat/colmap"), [("a.png", "b.png")], opts, "video")
    models = incremental(db, Path("ws/images"), Path("ws/.plantsplat/colmap/inc"), opts)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import sqlite3
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import native_stderr_silenced
from plantsplat.log import get_logger
from plantsplat.workers import WORKER_LOG, spawn_worker, stop_worker, worker_said

log = get_logger(__name__)

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
MAP_THREADS = 1
"""Threads of the mappers and bundle adjustments. With two, the incremental mapper gave one of two models of the same
matches at random (about one run in six, 2026-11-26); with one it gives the same model every time, as fast."""
RETRIANGULATED_BA_ITERATIONS = 100
"""Iterations, at most, of the bundle adjustment after :func:`retriangulate`."""
ROUND_BA_ITERATIONS = 10
"""Iterations, at most, of the bundle adjustment after :func:`retriangulate` in each round of localising left-out
frames (:func:`plantsplat.poses.estimate.localize_in_rounds`): the distortion test's and the cube's adjustments follow.
Replayed on own seed 216's 5 rounds (2026-11-28), 10, 25 and 100 gave the same rotation median and worst frame
within 0.01 degree."""
MATCH_THREADS = 1
"""Threads of SIFT matching and two-view verification. With two, COLMAP's CPU matcher returned different matches for
one or two of 988 pairs in about one run in five (2026-11-27), enough to move the mapping; one thread gives the same
matches every time, at about 1.4 times the matching time (22 s instead of 15 s for 988 pairs); :func:`match_pairs`
runs several one-thread processes instead."""
MIN_PAIRS_PER_WORKER = 50
"""Pairs below which another matching process costs more (start-up, a database copy) than it saves."""
MAPPED_DIR = "models"
"""Where the global mapping process leaves its models, one numbered folder each, largest first."""
WORKER_POLL_S = 0.2
"""How often the matching processes are looked at (a failed one stops the others at once)."""


@dataclass
class SfmConfig:
    """COLMAP settings of one SfM run. The user's options come from :class:`plantsplat.poses.PosesConfig`
    (:meth:`~plantsplat.poses.PosesConfig.sfm_options`), the one source of their defaults; the rest are fixed here."""

    camera_model: str
    max_features: int
    first_octave: int
    num_threads: int
    seed: int
    verbose: bool
    ba_loss_px: float
    peak_threshold: float = 0.004
    max_image_size: int = 1600
    ransac_max_trials: int = 2000
    min_pose_inliers: int = 15
    min_pose_inlier_ratio: float = 0.1
    guided_matching: bool = False
    """After a pair verifies, match its features again, each only with those near its epipolar line under the pair's
    verified geometry (COLMAP's guided matching): more inliers than the ratio test lets through on repeated texture."""


@contextlib.contextmanager
def colmap_logging(verbose: bool, keep_errors: bool = False):
    """Silence COLMAP's output on stderr unless ``verbose`` (restored afterwards).

    glog's level is raised to errors, and file descriptor 2 is sent to /dev/null for the duration
    (:func:`plantsplat.io.native_stderr_silenced`) because some pycolmap calls (bundle adjustment) print
    their reports regardless of the level. Do not log from inside this block: it would be swallowed too.
    ``keep_errors``: COLMAP's errors still reach stderr (a worker process, whose stderr is its log file).
    """
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    if verbose:
        yield
        return
    old = pycolmap.logging.minloglevel
    old_v = pycolmap.logging.verbose_level
    pycolmap.logging.minloglevel = 2  # errors only
    pycolmap.logging.verbose_level = 0
    try:
        with contextlib.nullcontext() if keep_errors else native_stderr_silenced():
            yield
    finally:
        pycolmap.logging.minloglevel = old
        pycolmap.logging.verbose_level = old_v


def extract_features(image_dir: Path, names: list[str], work_dir: Path, opts: SfmConfig) -> Path:
    """SIFT features of ``names`` (one shared camera) into ``work_dir/database.db``, rebuilt from scratch."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    if opts.camera_model not in CAMERA_MODELS:
        raise PlantsplatError(f"--camera-model {opts.camera_model!r}: use one of {', '.join(CAMERA_MODELS)}", exit_code=2)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    for p in (db, work_dir / "database.db-wal", work_dir / "database.db-shm"):
        p.unlink(missing_ok=True)
    pycolmap.set_random_seed(opts.seed)
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts.num_threads
    ext.max_image_size = opts.max_image_size
    ext.sift.max_num_features = opts.max_features
    ext.sift.peak_threshold = opts.peak_threshold
    ext.sift.first_octave = opts.first_octave
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    with colmap_logging(opts.verbose):
        # images first, one by one in name order: their ids (which the mappers' choices follow) are then the same on
        # every run, where the threaded extractor numbers them in the order its threads finish
        pycolmap.Database.open(str(db)).close()
        pycolmap.import_images(db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=sorted(names),
                               options=reader)
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    return db


def extracted_names(db: Path) -> set[str]:
    """The frames the database holds: COLMAP leaves out, without a word, a frame it cannot read."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    with pycolmap.Database.open(str(db)) as d:
        return {im.name for im in d.read_all_images()}


def _matching_options(opts: SfmConfig):
    """pycolmap's matching and two-view verification options for ``opts`` (one thread, seeded RANSAC)."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = MATCH_THREADS
    mopts.guided_matching = opts.guided_matching
    verif = pycolmap.TwoViewGeometryOptions()
    verif.ransac.random_seed = opts.seed
    verif.ransac.max_num_trials = opts.ransac_max_trials
    verif.detect_watermark = False
    return mopts, verif


def match_pairs(db: Path, work_dir: Path, pairs: list[tuple[str, str]], opts: SfmConfig, tag: str) -> None:
    """Match and verify image ``pairs`` (names) into ``db``; pairs matched before are skipped by COLMAP.

    With ``opts.num_threads`` > 1 the pairs are dealt out to that many processes
    (:mod:`plantsplat.poses.match_worker`), each matching on one thread into its own copy of the database, and their
    matches are gathered into ``db``. A pair's matches and verified geometry
    depend on that pair alone (seeded RANSAC; tested), so the database holds the same rows one process would write,
    where COLMAP's own threads change one or two pairs' matches in about one run in five (:data:`MATCH_THREADS`)."""
    workers = max(1, min(opts.num_threads, len(pairs) // MIN_PAIRS_PER_WORKER))
    finish_matching(start_matching(db, work_dir, pairs, opts, tag, 0 if workers == 1 else workers))


@dataclass
class MatchJob:
    """Matching processes started by :func:`start_matching` (none when it matched in this process)."""

    db: Path
    parts: list[Path] = dataclasses.field(default_factory=list)
    procs: list[subprocess.Popen] = dataclasses.field(default_factory=list)


def start_matching(db: Path, work_dir: Path, pairs: list[tuple[str, str]], opts: SfmConfig, tag: str,
                   processes: int) -> MatchJob:
    """Start matching ``pairs`` into ``db`` in ``processes`` one-thread processes (each on its own copy of ``db``) and
    return at once; :func:`finish_matching` waits for them and gathers their matches. With ``processes`` 0 the pairs
    are matched here before it returns. Work that needs one core can go on meanwhile, such as learning the
    vocabulary that chooses the next pairs; the copies are made now, so matches gathered into ``db`` later are not in
    them (a pair the database held is skipped, so give each job pairs of its own)."""
    job = MatchJob(db)
    if not pairs:
        return job
    write_pairs(work_dir / f"pairs_{tag}.txt", pairs)  # what was matched
    if processes == 0:
        match_pair_list(db, work_dir / f"pairs_{tag}.txt", opts)
        return job
    for stale in work_dir.glob(f"match_{tag}_*"):  # an interrupted run's copies
        shutil.rmtree(stale, ignore_errors=True)
    job.parts = [work_dir / f"match_{tag}_{k}" for k in range(processes)]
    try:
        job.procs.extend(_start_worker(db, part, pairs[k::processes], opts) for k, part in enumerate(job.parts))
    except BaseException:
        stop_matching(job)
        raise
    return job


def finish_matching(job: MatchJob) -> None:
    """Wait for the processes of :func:`start_matching` and gather their matches into its database."""
    try:
        _wait_workers(job.db, job.procs, job.parts)
        for part in job.parts:
            _gather_matches(job.db, part / "database.db")
    finally:
        stop_matching(job)


def stop_matching(job: MatchJob) -> None:
    """End the job's processes that still run (Ctrl-C or an error: no worker goes on matching) and remove their
    copies of the database; a failed worker's log stays."""
    for proc in job.procs:
        stop_worker(proc)
    for part in job.parts:
        for f in part.glob("database.db*"):
            f.unlink(missing_ok=True)
        if not (part / WORKER_LOG).is_file() or all(p.returncode == 0 for p in job.procs):
            shutil.rmtree(part, ignore_errors=True)


def _wait_workers(db: Path, procs: list[subprocess.Popen], parts: list[Path]) -> None:
    """Wait for every matching process; the first that fails stops them all with a one-line error."""
    while not all(p.poll() == 0 for p in procs):
        for proc, part in zip(procs, parts):
            if proc.poll() not in (None, 0):
                raise PlantsplatError(f"{db}: a matching process ended with code {proc.returncode} "
                                      f"({worker_said(part)}); re-run with --poses.num-threads 1 to match in "
                                      "this process")
        time.sleep(WORKER_POLL_S)


def _start_worker(db: Path, part: Path, pairs: list[tuple[str, str]], opts: SfmConfig) -> subprocess.Popen:
    """A matching process for ``pairs`` on a copy of ``db`` in the fresh folder ``part`` (its output in ``log.txt``)."""
    _fresh(part)
    copy_database(db, part / "database.db")
    write_pairs(part / "pairs.txt", pairs)
    here = part.resolve()
    return spawn_worker("plantsplat.poses.match_worker", [str(here / "database.db"), str(here / "pairs.txt"),
                                                          json.dumps(dataclasses.asdict(opts))], here)


def write_pairs(path: Path, pairs: list[tuple[str, str]]) -> None:
    """Image-name pairs, one per line: COLMAP's imported pairing list."""
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))


def match_pair_list(db: Path, pair_file: Path, opts: SfmConfig, keep_errors: bool = False) -> None:
    """Match and verify the pairs listed in ``pair_file`` (:func:`write_pairs`) into ``db`` in this process, on
    :data:`MATCH_THREADS` threads. ``keep_errors``: COLMAP's errors reach stderr (see :func:`colmap_logging`)."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    mopts, verif = _matching_options(opts)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_file)
    with colmap_logging(opts.verbose, keep_errors):
        pycolmap.match_image_pairs(db, matching_options=mopts, pairing_options=pairing, verification_options=verif,
                                   device=pycolmap.Device.cpu)


def copy_database(src: Path, dst: Path) -> None:
    """A consistent copy of a COLMAP database (SQLite's backup, whatever its journal holds)."""
    with contextlib.closing(sqlite3.connect(src)) as a, contextlib.closing(sqlite3.connect(dst)) as b:
        a.backup(b)


def _gather_matches(db: Path, part: Path) -> None:
    """The matches and verified two-view geometries of the database copy ``part`` into ``db`` (pairs ``db`` holds
    already are kept as they are: the copy holds them unchanged)."""
    with contextlib.closing(sqlite3.connect(db)) as c:
        c.execute("ATTACH DATABASE ? AS part", (str(part),))
        for table in ("matches", "two_view_geometries"):
            c.execute(f"INSERT OR IGNORE INTO main.{table} SELECT * FROM part.{table}")
        c.commit()
        c.execute("DETACH DATABASE part")


def match_exhaustive(db: Path, opts: SfmConfig) -> None:
    """Match and verify every pair of frames in ``db``."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    mopts, verif = _matching_options(opts)
    with colmap_logging(opts.verbose):
        pycolmap.match_exhaustive(db, matching_options=mopts, verification_options=verif, device=pycolmap.Device.cpu)


def _fresh(out_dir: Path) -> None:
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)


def incremental(db: Path, image_dir: Path, out_dir: Path, opts: SfmConfig, input_path: Path | None = None) -> list:
    """COLMAP incremental mapping (continuing the model at ``input_path`` if given); models found, largest first."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    _fresh(out_dir)
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = MAP_THREADS
    o.random_seed = opts.seed
    o.mapper.random_seed = opts.seed
    o.triangulation.random_seed = opts.seed
    o.min_model_size = 3
    pycolmap.set_random_seed(opts.seed)  # whatever ran before in this process: the same draws
    o.mapper.abs_pose_min_num_inliers = opts.min_pose_inliers
    o.mapper.abs_pose_min_inlier_ratio = opts.min_pose_inlier_ratio
    with colmap_logging(opts.verbose):
        models = pycolmap.incremental_mapping(db, image_dir, out_dir, options=o,
                                              input_path=str(input_path) if input_path else "")
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


def global_mapping(db: Path, image_dir: Path, out_dir: Path, opts: SfmConfig) -> list:
    """GLOMAP-style global mapping (rotation averaging, global positioning, bundle adjustment); largest first."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    _fresh(out_dir)
    o = pycolmap.GlobalPipelineOptions()
    o.num_threads = MAP_THREADS
    o.random_seed = opts.seed
    o.mapper.num_threads = MAP_THREADS
    o.mapper.random_seed = opts.seed
    o.mapper.global_positioning.use_gpu = False
    pycolmap.set_random_seed(opts.seed)
    o.mapper.bundle_adjustment.ceres.use_gpu = False
    with colmap_logging(opts.verbose):
        models = pycolmap.global_mapping(db, image_dir, out_dir, options=o)
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


def global_then_incremental(db: Path, image_dir: Path, out_dir: Path, opts: SfmConfig) -> list:
    """Global mapping, then COLMAP's incremental mapper continued from its largest model (frames it left out are
    registered, points triangulated again, bundle adjustment); largest first. The global solve closes the orbit's
    loop over every pair at once; the continuation repairs the cameras it placed badly."""
    models = global_mapping(db, image_dir, out_dir / "global", opts)
    if not models:
        return []
    write_model(models[0], out_dir / "seed", opts.verbose)
    try:
        cont = incremental(db, image_dir, out_dir / "continued", opts, input_path=out_dir / "seed")
    except Exception as exc:  # COLMAP refuses a seed it cannot extend: keep the global model
        log.debug("continued mapping failed: %s", exc)
        cont = []
    return cont if cont and cont[0].num_reg_images() >= models[0].num_reg_images() else models


def start_global_mapping(db: Path, image_dir: Path, out_dir: Path, opts: SfmConfig) -> subprocess.Popen:
    """:func:`global_then_incremental` in a process of its own (:mod:`plantsplat.poses.map_worker`), on a copy of
    ``db`` taken now, in the fresh folder ``out_dir``; :func:`finish_global_mapping` collects its models. It runs on
    one thread beside the incremental mapper in this process, each on a core of its own."""
    _fresh(out_dir)
    copy_database(db, out_dir / "database.db")
    here = out_dir.resolve()
    return spawn_worker("plantsplat.poses.map_worker", [str(here / "database.db"), str(Path(image_dir).resolve()),
                                                        str(here), json.dumps(dataclasses.asdict(opts))], here)


def finish_global_mapping(proc: subprocess.Popen, out_dir: Path) -> list:
    """The models of the process :func:`start_global_mapping` started in ``out_dir`` (largest first), once it ends; a
    one-line error naming its log when it fails."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    if proc.wait() != 0:
        raise PlantsplatError(f"{out_dir}: the global mapping process ended with code {proc.returncode} "
                              f"({worker_said(out_dir)}); re-run with --poses.num-threads 1 to map in this process")
    done = out_dir / MAPPED_DIR
    models = [pycolmap.Reconstruction(str(done / k)) for k in sorted((p.name for p in done.iterdir()), key=int)]
    (out_dir / "database.db").unlink(missing_ok=True)
    return models


def write_models(models: list, out_dir: Path, verbose: bool = False) -> None:
    """``models`` as COLMAP binary models in ``out_dir/0``, ``out_dir/1``, ... (in their order), ``out_dir`` fresh."""
    _fresh(out_dir)
    for k, rec in enumerate(models):
        write_model(rec, out_dir / str(k), verbose)


def write_model(rec, out_dir: Path, verbose: bool = False) -> None:
    """Write a model as COLMAP binary into a fresh ``out_dir`` (a seed for continued mapping)."""
    _fresh(out_dir)
    with colmap_logging(verbose):
        rec.write_binary(str(out_dir))


def n_threads_env(n: int) -> None:
    """Cap OpenMP/BLAS threads used inside COLMAP's dependencies."""
    os.environ.setdefault("OMP_NUM_THREADS", str(n))


def merge_models(models: list, db: Path, image_dir: Path, work_dir: Path, opts: SfmConfig):
    """One model from the pieces incremental mapping left: each piece that shares frames with the first is
    aligned onto it by the reprojections of their common points (COLMAP's model alignment), its other frames
    join, then every match is triangulated again and the whole is bundle-adjusted. Returns the merged model,
    or None when no piece could be aligned."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    base = models[0]
    poses = {im.name: im.cam_from_world() for im in base.images.values() if im.has_pose}
    joined = 0
    for other in models[1:]:
        common = {im.name for im in other.images.values() if im.has_pose} & set(poses)
        if len(common) < 3:
            continue
        with colmap_logging(opts.verbose):
            sim = pycolmap.align_reconstructions_via_reprojections(other, base)
        if sim is None:
            continue
        moved = pycolmap.Reconstruction(other)
        moved.transform(sim)
        for im in moved.images.values():
            if im.has_pose and im.name not in poses:
                poses[im.name] = im.cam_from_world()
                joined += 1
    if not joined:
        return None
    return retriangulate(base, poses, db, image_dir, work_dir, opts)


def ba_options(refine_distortion: bool, num_threads: int):
    """COLMAP's options for a bundle adjustment of a mapped model on the CPU: focal length refined (the lens distortion
    too with ``refine_distortion``), principal point fixed, no summary printed."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = True
    opts.refine_extra_params = refine_distortion
    opts.refine_principal_point = False
    opts.print_summary = False
    opts.ceres.use_gpu = False
    opts.ceres.solver_options.num_threads = num_threads
    return opts


def final_ba_options(refine_distortion: bool, num_threads: int, loss_scale_px: float, iterations: int):
    """:func:`ba_options` with a Cauchy loss of scale ``loss_scale_px`` on each reprojection error, so that the few
    matches left off by pixels do not pull the focal length and the cameras, and at most ``iterations`` iterations."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    opts = ba_options(refine_distortion, num_threads)
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    opts.ceres.loss_function_scale = loss_scale_px
    opts.ceres.solver_options.max_num_iterations = iterations
    return opts


def retriangulate(like, poses: dict, db: Path, image_dir: Path, work_dir: Path, opts: SfmConfig,
                  iterations: int = RETRIANGULATED_BA_ITERATIONS):
    """A model of the frames in ``poses`` (name -> cam_from_world) with the camera of ``like``: every match in
    ``db`` triangulated, then a bundle adjustment (at most ``iterations``) of poses, points and intrinsics with the
    Cauchy loss of ``opts.ba_loss_px``, as every adjustment after mapping (:func:`final_ba_options`)."""
    import pycolmap  # deferred: pycolmap is heavy, and the CLI starts without it

    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        cam_id = d.read_all_cameras()[0].camera_id
    cam = like.cameras[next(iter(like.cameras))]
    rec = pycolmap.Reconstruction()
    new_cam = pycolmap.Camera.create_from_model_name(cam_id, cam.model.name, cam.focal_length_x, cam.width, cam.height)
    new_cam.params = cam.params
    rec.add_camera_with_trivial_rig(new_cam)
    for name, pose in poses.items():
        im = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=cam_id, image_id=ids[name])
        rec.add_image_with_trivial_frame(im, pose)
    _fresh(work_dir)
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = MAP_THREADS
    o.random_seed = opts.seed
    o.triangulation.random_seed = opts.seed
    pycolmap.set_random_seed(opts.seed)
    ba = final_ba_options(True, MAP_THREADS, opts.ba_loss_px, iterations)
    with colmap_logging(opts.verbose):
        rec = pycolmap.triangulate_points(rec, db, image_dir, work_dir, clear_points=True, options=o,
                                          refine_intrinsics=True)
        pycolmap.bundle_adjustment(rec, ba)
    return rec

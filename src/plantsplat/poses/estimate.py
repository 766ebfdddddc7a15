"""The poses stage: SfM (or an imported model) -> metric cube frame -> COLMAP/nerfstudio outputs.

:func:`estimate_poses` is the library entry point used by ``plantsplat poses`` and ``plantsplat run``.

Robust default (``mapper='auto'``), because COLMAP's defaults split or break plant-orbit videos:

1. incremental mapping; every model found is checked against the cube (its markers must reproject
   where they are detected) and calibrated into the cube frame;
2. consistent fragments are merged in the cube frame (the cube is their common reference), all
   matches are re-triangulated with the merged poses and the whole model is bundle-adjusted;
3. frames still missing get extra pairs (to the registered frames nearest to their registered video
   neighbours) and incremental mapping continues from the model;
4. if fewer than ``min_registered`` of the frames are in, global mapping (rotation averaging +
   global positioning) is run and kept when it registers more frames with a consistent cube;
5. the final model is calibrated (scale, gravity, origin), bundle-adjusted with the cube's marker
   corners as fixed control points, and written out.

Example:
    >>> from plantsplat.poses import PosesConfig, estimate_poses
    >>> report = estimate_poses(Workspace("ws/plant_01"), PosesConfig())   # doctest: +SKIP
    >>> report["registered"], report["total"], report["scale_source"]      # doctest: +SKIP
    (120, 120, 'aruco')
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.io import read_json, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.workspace import Workspace

log = get_logger(__name__)

MIN_FRAMES = 3
WORK_DIR = ".plantsplat/colmap"


@dataclass
class PosesConfig:
    """Options of the poses stage."""

    matcher: Literal["auto", "guided", "exhaustive", "sequential"] = "auto"
    """Pairs to match: guided (video neighbours + frames seeing the cube from similar directions), exhaustive, sequential (video order), auto (guided when most frames see the cube)."""
    mapper: Literal["auto", "incremental", "global"] = "auto"
    """Mapping: auto (incremental, cube-checked fragment merge, global fallback), incremental, global."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "RADIAL"
    """COLMAP camera model shared by all frames (phones: RADIAL)."""
    max_features: int = 2048
    """SIFT features per frame."""
    sift_first_octave: int = -1
    """SIFT first octave: -1 upsamples frames 2x (more small features, COLMAP's default); 0 is faster."""
    import_colmap: Path | None = None
    """Use this COLMAP model (folder with cameras/images/points3D, .bin or .txt) instead of running SfM."""
    import_transforms: Path | None = None
    """Use this nerfstudio transforms.json instead of running SfM."""
    calibrate: bool = True
    """Calibrate scale, gravity and origin with the ArUco cube (--no-calibrate keeps the model as it is)."""
    max_residual_px: float = 3.0
    """Marker detections reprojecting worse than this (pixels) are rejected; the model check uses it too."""
    cube_bundle_adjustment: bool = True
    """After calibration, bundle-adjust with the cube's marker corners as fixed control points (SfM only, not imports)."""
    min_registered: float = 0.8
    """Fail (exit code 3) when fewer than this fraction of the frames register."""
    cube_size: float = 10.0
    """Cube edge (cm)."""
    marker_size: float = 9.6
    """Marker side, black border included (cm)."""
    dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the cube's markers."""
    num_threads: int = 2
    """CPU threads for COLMAP."""
    seed: int = 0
    """Random seed (COLMAP's RANSAC and mapper)."""
    colmap_log: bool = False
    """Show COLMAP's own log on stderr (also on with the global --verbose)."""

    def cube(self) -> CubeSpec:
        return CubeSpec(size=self.cube_size, marker_size=self.marker_size, dictionary=self.dictionary)

    def sfm_options(self):
        from plantsplat.poses.sfm import SfmOptions

        return SfmOptions(
            camera_model=self.camera_model,
            matcher=self.matcher,
            mapper=self.mapper,
            max_features=self.max_features,
            first_octave=self.sift_first_octave,
            num_threads=self.num_threads,
            seed=self.seed,
            verbose=self.colmap_log,
        )


def _fingerprint(cfg: PosesConfig, names: list[str], ws: Workspace) -> str:
    d = {k: str(v) for k, v in asdict(cfg).items() if k not in ("colmap_log", "num_threads")}
    d["images"] = names
    d["frames_json"] = (
        hashlib.sha1(ws.frames_json.read_bytes()).hexdigest() if ws.frames_json.is_file() else None
    )
    for k in ("import_colmap", "import_transforms"):
        p = getattr(cfg, k)
        if p is not None:
            d[k] = str(Path(p).resolve())
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def outputs(ws: Workspace) -> list[Path]:
    """Files the poses stage writes."""
    return [ws.sparse_dir, ws.sparse_text_dir, ws.transforms_json, ws.poses_json, ws.sparse_points_ply]


def _name_map(ws: Workspace, model_names: list[str], names: list[str]) -> dict[str, str]:
    """Map an imported model's image names onto workspace image names (same name, or frames.json source name)."""
    have = set(names)
    direct = {n: n for n in model_names if n in have}
    if len(direct) == len(model_names) or not ws.frames_json.is_file():
        return direct
    try:
        frames = read_json(ws.frames_json).get("frames", [])
    except PlantsplatError:
        return direct
    by_source = {Path(f["source_name"]).name: f["name"] for f in frames if f.get("source_name")}
    out = dict(direct)
    for n in model_names:
        if n not in out and Path(n).name in by_source and by_source[Path(n).name] in have:
            out[n] = by_source[Path(n).name]
    return out


def _rename_images(rec, mapping: dict[str, str]):
    """A copy of ``rec`` keeping only images in ``mapping``, renamed to workspace names (poses, camera, points kept)."""
    import pycolmap

    out = pycolmap.Reconstruction()
    cam_ids = set()
    id_map = {}
    for im in rec.images.values():
        if im.has_pose and im.name in mapping:
            cam_ids.add(im.camera_id)
    if len(cam_ids) != 1:
        raise PlantsplatError(
            f"the imported model uses {len(cam_ids)} cameras for the workspace frames; plantsplat expects one shared camera"
        )
    cam = rec.cameras[next(iter(cam_ids))]
    new_cam = pycolmap.Camera.create_from_model_name(1, cam.model.name, cam.focal_length_x, cam.width, cam.height)
    new_cam.params = cam.params
    out.add_camera_with_trivial_rig(new_cam)
    for im in sorted(rec.images.values(), key=lambda i: mapping.get(i.name, "~")):
        if not (im.has_pose and im.name in mapping):
            continue
        new = pycolmap.Image(name=mapping[im.name], keypoints=np.zeros((0, 2)), camera_id=1, image_id=len(id_map) + 1)
        out.add_image_with_trivial_frame(new, im.cam_from_world())
        id_map[im.image_id] = new.image_id
    return out


def _registered_names(rec) -> set[str]:
    return {im.name for im in rec.images.values() if im.has_pose}


def _merge_in_cube_frame(frags: list, db: Path, image_dir: Path, work: Path, opts, adjust: bool = True,
                         skip: frozenset[str] = frozenset()):
    """Merge fragments already transformed into the cube frame; re-triangulate and bundle-adjust.

    A frame posed in several fragments takes its pose from the first; the camera's intrinsics come
    from the first fragment; frames named in ``skip`` are left out. With ``adjust=False`` poses and
    intrinsics stay as given and only the points are triangulated.
    """
    import pycolmap

    from plantsplat.poses.sfm import refine

    with pycolmap.Database.open(str(db)) as d:
        db_ids = {im.name: im.image_id for im in d.read_all_images()}
        db_cam = d.read_all_cameras()[0]
    base = frags[0]
    cam = base.cameras[next(iter(base.cameras))]
    merged = pycolmap.Reconstruction()
    new_cam = pycolmap.Camera.create_from_model_name(db_cam.camera_id, cam.model.name, cam.focal_length_x, cam.width, cam.height)
    new_cam.params = cam.params
    merged.add_camera_with_trivial_rig(new_cam)
    done = set()
    for frag in frags:
        for im in frag.images.values():
            if not im.has_pose or im.name in done or im.name in skip or im.name not in db_ids:
                continue
            new = pycolmap.Image(name=im.name, keypoints=np.zeros((0, 2)), camera_id=db_cam.camera_id, image_id=db_ids[im.name])
            merged.add_image_with_trivial_frame(new, im.cam_from_world())
            done.add(im.name)
    return refine(merged, db, image_dir, work, opts, retriangulate=True, adjust=adjust)


def _frames_off_the_cube(cal, detections: dict, limit_px: float) -> frozenset[str]:
    """Frames all of whose marker detections reproject more than ``limit_px`` from the model's cube.

    One marker far off is a bad detection; every marker of a frame far off is a wrong pose (against the
    renderer's cameras, the detections of the batch benchmark's 72-frame captures lie within 4.4 px).
    """
    off: dict[str, set] = {}
    for name, mid, r in cal.detections_rejected:
        if r > limit_px:
            off.setdefault(name, set()).add(mid)
    return frozenset(n for n, mids in off.items() if mids >= set(detections[n]))


def _source_positions(ws: Workspace, names: list[str]) -> list[int] | None:
    """Each frame's number in the source video (``frames.json``); None for photos or when not recorded."""
    if not ws.frames_json.is_file():
        return None
    try:
        info = read_json(ws.frames_json)
        if info.get("kind") != "video":
            return None
        src = {f["name"]: f["source_index"] for f in info.get("frames", [])}
    except (PlantsplatError, KeyError, TypeError, AttributeError):
        return None
    return [src[n] for n in names] if all(isinstance(src.get(n), int) for n in names) else None


def _composed(new, old):
    """Calibration ``new`` (found in the frame ``old`` maps into) made to map the original model frame."""
    m = new.matrix() @ old.matrix()
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    new.scale, new.R, new.t = s, m[:3, :3] / s, m[:3, 3]
    return new


def wrongly_posed(rec, cal, detections: dict, names: list[str], max_residual_px: float,
                  positions: list[int] | None = None) -> list[str]:
    """Frames of a model in the cube frame whose poses are wrong, though SfM registered them.

    Two signs: every marker the frame shows reprojects more than twice ``max_residual_px`` from the
    cube (:func:`_frames_off_the_cube`), or the camera leaves the path through its video neighbours
    (:func:`~plantsplat.segment.geometry.orbit_outliers`, which also checks frames without markers).
    ``positions`` (increasing) place the frames of a video in time (their source frame numbers; kept
    frames are not evenly spaced), and each frame is checked against its nearest neighbours. Without
    them (photos: a new ring may start a step away from the last) a frame is kept when any pair of
    neighbours on either side predicts it (``any_side``), which misses a run of wrong frames at the
    start or end of the capture.
    On the batch benchmark's captures cut to 72 frames at 360x640 (15 degrees between neighbours)
    COLMAP registered 5-8 frames (single ones and runs of up to four) 5-59 degrees off (against the
    renderer's cameras) in three runs; the cube check alone misses them, as most show no marker.
    """
    from plantsplat.segment.geometry import orbit_centre, orbit_outliers

    # a model that fails the cube check is no reference for single frames: only their path is checked then
    off = _frames_off_the_cube(cal, detections, 2 * max_residual_px) if cal is not None and cal.consistent else frozenset()
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    any_side = positions is None or any(b <= a for a, b in zip(positions, positions[1:]))
    positions = list(range(len(names))) if any_side else [int(x) for x in positions]
    at = {x - positions[0]: n for x, n in zip(positions, names)}
    poses: list[np.ndarray | None] = [None] * (positions[-1] - positions[0] + 1) if names else []
    for k, n in at.items():
        if n in by_name and n not in off:
            T = np.eye(4)
            T[:3] = by_name[n].cam_from_world().matrix()
            poses[k] = T
    centre = orbit_centre(poses) if sum(p is not None for p in poses) >= 3 else None
    path = {at[i] for i in orbit_outliers(poses, centre, any_side=any_side)} if centre is not None else set()
    return sorted((set(off) & set(by_name)) | path)


def _cube_adjusted(rec, cal, detections: dict, cube: CubeSpec, cfg: PosesConfig, db: Path, image_dir: Path, work: Path):
    """A model that fails the cube check, bundle-adjusted with the cube's marker corners as control points.

    Joining fragments or extending a model can leave it slightly warped as a whole: on a 72-frame
    capture of the batch benchmark two fragments that each passed the check (1.5 px) merged into a
    model whose scale had drifted by 5 % in its plain bundle adjustment (2.5 px, a quarter of the
    detections beyond ``max_residual_px``). A copy of ``rec`` in the cube frame is adjusted with the
    corners held fixed (:func:`~plantsplat.poses.calibrate.refine_with_cube`). Frames whose every
    marker still lies more than twice ``max_residual_px`` off are posed wrongly and are left out
    (a later step may register them again). If the rest passes the check, its poses and intrinsics
    are returned as a new model with points re-triangulated from the matches. Only detections within
    twice ``max_residual_px`` pull on the cameras, so markers far off (a wrong pose) pull on nothing.
    Returns ``(model, calibration, frames left out)`` or ``None``.
    """
    adjusted = _adjust_onto_cube(rec, cal, detections, cube, cfg)
    if adjusted is None:
        return None
    trial, drop = adjusted
    out = _merge_in_cube_frame([trial], db, image_dir, work, cfg.sfm_options(), adjust=False, skip=drop)
    ocal = _check_and_calibrate([out], detections, cube, cfg)[0]
    if ocal is None or not ocal.consistent:
        return None
    return out, ocal, drop


def _adjust_onto_cube(rec, cal, detections: dict, cube: CubeSpec, cfg: PosesConfig):
    """The bundle adjustment of :func:`_cube_adjusted`: ``(adjusted copy in the cube frame, frames left out)`` or None."""
    import pycolmap

    from plantsplat.poses.calibrate import calibrate, refine_with_cube
    from plantsplat.poses.sfm import colmap_logging

    if cal is None or cal.consistent or not np.isfinite(rec.compute_mean_reprojection_error()):
        return None
    trial = pycolmap.Reconstruction(rec)
    trial.transform(cal.to_pycolmap())
    with colmap_logging(cfg.colmap_log):
        n_ctrl = refine_with_cube(trial, detections, cal, cube, cfg.num_threads, within_px=2 * cfg.max_residual_px)
    if not n_ctrl:
        return None
    tcal = calibrate(trial, detections, cube, cfg.max_residual_px)
    drop: frozenset[str] = frozenset()
    if tcal is not None and not tcal.consistent:
        drop = _frames_off_the_cube(tcal, detections, 2 * cfg.max_residual_px)
        if drop and len(drop) < 0.2 * trial.num_reg_images():
            tcal = calibrate(trial, {n: d for n, d in detections.items() if n not in drop}, cube, cfg.max_residual_px)
    if tcal is None or not tcal.consistent:
        return None
    trial.transform(tcal.to_pycolmap())
    return trial, drop


def _check_and_calibrate(models: list, detections: dict, cube: CubeSpec, cfg: PosesConfig):
    from plantsplat.poses.calibrate import calibrate

    out = []
    for i, rec in enumerate(models):
        cal = calibrate(rec, detections, cube, cfg.max_residual_px) if detections else None
        out.append(cal)
        err = rec.compute_mean_reprojection_error()
        log.info(
            "  model %d: %d frames, reprojection %s, cube %s",
            i,
            rec.num_reg_images(),
            f"{err:.2f} px" if np.isfinite(err) and err < 1e3 else "diverged",
            "not seen" if cal is None else f"residual {cal.median_residual_px:.2f} px ({'consistent' if cal.consistent else 'INCONSISTENT'})",
        )
    return out


def _run_sfm(ws: Workspace, names: list[str], cfg: PosesConfig, detections: dict, cube: CubeSpec, report: dict):
    """Run SfM with the robust strategy; returns the chosen reconstruction (model frame)."""
    from plantsplat.poses import sfm

    opts = cfg.sfm_options()
    work = ws.root / WORK_DIR
    timings = report["timings"]
    directions = {}
    if detections and opts.matcher in ("auto", "guided"):
        from plantsplat.io import read_image

        h, w = read_image(ws.images_dir / names[0], mode="gray").shape
        directions = sfm.view_directions(detections, (w, h), cube)
    db, matcher, t = sfm.extract_and_match(ws.images_dir, names, work, opts, directions)
    timings.update(t)
    report["matcher"] = matcher
    n = len(names)
    events = report["events"]

    def cube_checked(m, c, what: str):
        """``(m, c)``, or ``m`` adjusted onto the cube when that makes a model failing the check pass.

        Only a model with more frames than the current one is worth it: only such a model can replace it.
        """
        if m.num_reg_images() <= rec.num_reg_images():
            return m, c
        fixed = _cube_adjusted(m, c, detections, cube, cfg, db, ws.images_dir, work / "cube_adjusted")
        if fixed is None:
            return m, c
        m2, c2, drop = fixed
        left = f"; {len(drop)} frame(s) posed off the cube left out: {', '.join(sorted(drop))}" if drop else ""
        log.info("  %s passes the cube check after adjustment with the cube's corners: residual %.2f px%s",
                 what, c2.median_residual_px, left)
        events.append(f"{what}: warped as a whole, adjusted onto the cube's corners "
                      f"({c.median_residual_px:.1f} -> {c2.median_residual_px:.1f} px){left}")
        return m2, c2

    def score(rec, cal):
        ok = cal is None or cal.consistent
        return (ok, rec.num_reg_images(), -rec.compute_mean_reprojection_error())

    if cfg.mapper == "global":
        t0 = time.perf_counter()
        log.info("SfM: global mapping")
        models = sfm.global_sfm(db, ws.images_dir, work / "global", opts)
        timings["map_s"] = time.perf_counter() - t0
        report["mapper"] = "global"
    else:
        t0 = time.perf_counter()
        log.info("SfM: incremental mapping")
        models = sfm.incremental(db, ws.images_dir, work / "incremental", opts)
        timings["map_s"] = time.perf_counter() - t0
        report["mapper"] = "incremental"
    if not models:
        raise PlantsplatError(
            f"{ws.images_dir}: COLMAP could not reconstruct any model from {n} frames; "
            "the frames may be too blurry, too few or too far apart (keep 6-12 degrees between neighbours)"
        )
    report["models_found"] = [m.num_reg_images() for m in models]
    log.info("SfM: %d model(s) found: %s frames", len(models), report["models_found"])
    cals = _check_and_calibrate(models, detections, cube, cfg)
    best = max(range(len(models)), key=lambda i: score(models[i], cals[i]))
    rec, cal = models[best], cals[best]
    if best != 0:
        events.append(f"largest model ({models[0].num_reg_images()} frames) rejected: cube does not reproject on its markers")

    if cfg.mapper != "auto":
        report["models_merged"] = 1
        return rec, db

    # merge fragments that agree with the cube
    good = [(m, c) for m, c in zip(models, cals) if c is not None and c.consistent]
    bad = [i for i, (m, c) in enumerate(zip(models, cals)) if c is not None and not c.consistent]
    if bad:
        events.append(f"{len(bad)} model(s) rejected by the cube check: {[models[i].num_reg_images() for i in bad]} frames")
    report["models_merged"] = 1
    if len(good) > 1:
        t0 = time.perf_counter()
        frags = []
        for m, c in good:
            m.transform(c.to_pycolmap())
            frags.append(m)
        log.info("SfM: merging %d fragments in the cube frame", len(frags))
        merged = _merge_in_cube_frame(frags, db, ws.images_dir, work / "merge", opts)
        mcal = _check_and_calibrate([merged], detections, cube, cfg)[0]
        merged, mcal = cube_checked(merged, mcal, "merged model")
        if merged.num_reg_images() > rec.num_reg_images() and (mcal is None or mcal.consistent):
            events.append(f"merged {len(frags)} fragments ({[f.num_reg_images() for f in frags]} frames) in the cube frame")
            rec, cal = merged, mcal
            report["models_merged"] = len(frags)
        timings["merge_s"] = time.perf_counter() - t0

    # register what is still missing by continuing incremental mapping from the current model
    if rec.num_reg_images() < n:
        t0 = time.perf_counter()
        seed_dir = work / "seed"
        if seed_dir.exists():
            shutil.rmtree(seed_dir)
        seed_dir.mkdir(parents=True)
        with sfm.colmap_logging(opts.verbose):
            rec.write_binary(str(seed_dir))
        extra = sfm.pairs_for_missing(names, rec)
        log.info(
            "SfM: %d frames missing: matching %d more pairs around them, continuing incremental mapping",
            n - rec.num_reg_images(), len(extra),
        )
        if extra:
            sfm.match_pairs(db, work, extra, opts, "missing")
        try:
            cont = sfm.incremental(db, ws.images_dir, work / "continued", opts, input_path=seed_dir)
        except Exception as exc:  # COLMAP refuses a seed it cannot extend: keep what we have
            log.debug("continued mapping failed: %s", exc)
            cont = []
        if cont and cont[0].num_reg_images() > rec.num_reg_images():
            ccal = _check_and_calibrate(cont[:1], detections, cube, cfg)[0]
            cont[0], ccal = cube_checked(cont[0], ccal, "continued model")
            if ccal is None or ccal.consistent:
                events.append(f"continued mapping registered {cont[0].num_reg_images() - rec.num_reg_images()} more frames")
                rec, cal = cont[0], ccal
        timings["continue_s"] = time.perf_counter() - t0

    # global mapping as the last resort (less accurate, so only when too many frames are missing)
    if rec.num_reg_images() < cfg.min_registered * n:
        t0 = time.perf_counter()
        log.info("SfM: %d frames still missing, trying global mapping", n - rec.num_reg_images())
        glob = sfm.global_sfm(db, ws.images_dir, work / "global", opts)
        if glob:
            g = sfm.refine(glob[0], db, ws.images_dir, work / "global_refine", opts)
            gcal = _check_and_calibrate([g], detections, cube, cfg)[0]
            g, gcal = cube_checked(g, gcal, "global model")
            if g.num_reg_images() > rec.num_reg_images() and (gcal is None or gcal.consistent):
                events.append(f"global mapping registered {g.num_reg_images()} frames (incremental: {rec.num_reg_images()})")
                rec, cal = g, gcal
                report["mapper"] = "global"
        timings["global_s"] = time.perf_counter() - t0
    return rec, db


def estimate_poses(ws: Workspace | str | Path, cfg: PosesConfig | None = None, force: bool = False) -> dict:
    """Run the poses stage on workspace ``ws``; returns the ``poses.json`` report.

    Skips the work when ``poses.json`` and every output exist for the same images and options
    (pass ``force=True`` to redo). Raises :class:`PlantsplatError` on bad input (too few frames,
    broken import, too few frames registered); outputs of a partly registered capture are written
    before that error, so nothing is lost.
    """
    from plantsplat.poses.calibrate import detect_all, up_vector
    from plantsplat.poses.interop import read_colmap, read_transforms, write_colmap, write_points_ply, write_transforms
    from plantsplat.poses.sfm import colmap_logging, n_threads_env

    cfg = cfg or PosesConfig()
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    if cfg.import_colmap is not None and cfg.import_transforms is not None:
        raise UsageError("pass only one of --import-colmap and --import-transforms")
    ws.require(ws.images_dir, "frames")
    names = ws.image_names()
    if len(names) < MIN_FRAMES:
        raise PlantsplatError(
            f"{ws.images_dir}: only {len(names)} frame(s); structure from motion needs at least {MIN_FRAMES} "
            "(the paper uses 100-150); run `plantsplat frames` with more frames"
        )
    fp = _fingerprint(cfg, names, ws)
    if not force and ws.poses_json.is_file() and all(p.exists() for p in outputs(ws)):
        try:
            old = read_json(ws.poses_json)
        except PlantsplatError:
            old = {}
        if old.get("fingerprint") == fp:
            log.info("%s: poses already estimated (%d/%d frames); pass --force to redo", ws.root, old.get("registered", 0), old.get("total", 0))
            return old
    n_threads_env(cfg.num_threads)
    cube = cfg.cube()
    t_start = time.perf_counter()
    report: dict = {
        "fingerprint": fp,
        "total": len(names),
        "timings": {},
        "events": [],
        "camera_model": cfg.camera_model,
        "source": "sfm",
    }

    t0 = time.perf_counter()
    detections = detect_all(ws.images_dir, names, cube) if cfg.calibrate else {}
    report["timings"]["detect_markers_s"] = time.perf_counter() - t0
    report["frames_with_markers"] = len(detections)

    db = None
    if cfg.import_colmap is not None or cfg.import_transforms is not None:
        src = Path(cfg.import_colmap or cfg.import_transforms)
        if cfg.import_colmap is not None:
            with colmap_logging(cfg.colmap_log):
                raw = read_colmap(src)
            report["source"] = f"colmap:{src}"
        else:
            raw = read_transforms(src, None)
            report["source"] = f"transforms:{src}"
        mapping = _name_map(ws, [im.name for im in raw.images.values() if im.has_pose], names)
        if not mapping:
            raise PlantsplatError(
                f"{src}: none of its images matches a frame in {ws.images_dir} (by name or frames.json source name); "
                "import a model of these frames"
            )
        if cfg.import_colmap is not None and len(mapping) == raw.num_reg_images() and all(k == v for k, v in mapping.items()):
            rec = raw
        else:
            rec = _rename_images(raw, mapping)
            if raw.num_points3D():
                report["events"].append("imported points dropped (image names were remapped); no sparse points")
        report["matcher"] = report["mapper"] = "import"
        report["models_found"] = [rec.num_reg_images()]
        report["models_merged"] = 1
    else:
        rec, db = _run_sfm(ws, names, cfg, detections, cube, report)

    # final calibration into the cube frame
    from plantsplat.poses.calibrate import calibrate

    t0 = time.perf_counter()
    cal = None
    if cfg.calibrate and detections:
        cal = calibrate(rec, detections, cube, cfg.max_residual_px)
    if cal is not None:
        rec.transform(cal.to_pycolmap())
        if report["source"] == "sfm":
            drop = wrongly_posed(rec, cal, detections, names, cfg.max_residual_px, _source_positions(ws, names))
            if drop:
                by_name = {im.name: im for im in rec.images.values() if im.has_pose}
                for n in drop:
                    rec.deregister_frame(by_name[n].frame_id)
                log.warning(
                    "%d frame(s) left out: their poses disagree with the cube or leave the camera's path (%s)",
                    len(drop), ", ".join(drop[:10]) + (f" and {len(drop) - 10} more" if len(drop) > 10 else ""),
                )
                report["events"].append(f"{len(drop)} frame(s) posed off the cube or the camera path left out")
                report["wrongly_posed"] = drop
                cal2 = calibrate(rec, detections, cube, cfg.max_residual_px)
                if cal2 is not None:
                    rec.transform(cal2.to_pycolmap())
                    cal = _composed(cal2, cal)
    report["timings"]["calibrate_s"] = time.perf_counter() - t0
    if cal is not None and not cal.consistent:
        log.warning(
            "the cube's markers reproject %.1f px from their detections (%.0f%% of detections within %.1f px): "
            "the poses may be wrong; check poses.json",
            cal.median_residual_px, 100 * cal.inlier_ratio, cfg.max_residual_px,
        )
        report["events"].append("final model fails the cube check")
    if cal is not None:
        if cal.consistent and cfg.cube_bundle_adjustment and report["source"] == "sfm":
            from plantsplat.poses.calibrate import refine_with_cube

            t0 = time.perf_counter()
            log.info("bundle adjustment with the cube's marker corners as control points")
            with colmap_logging(cfg.colmap_log):
                n_ctrl = refine_with_cube(rec, detections, cal, cube, cfg.num_threads)
            if n_ctrl:
                cal2 = calibrate(rec, detections, cube, cfg.max_residual_px)
                if cal2 is not None and cal2.consistent:
                    rec.transform(cal2.to_pycolmap())  # a small correction: the control points fix the frame
                    cal = _composed(cal2, cal)
                report["events"].append(f"bundle adjustment with {n_ctrl} cube corners as control points")
            report["timings"]["cube_ba_s"] = time.perf_counter() - t0
        report["scale_source"] = "aruco"
        report["similarity"] = cal.summary()
        report["up_vector_model"] = up_vector(cal)
        report["marker_residuals_px"] = cal.frame_residuals_px
        report["units"] = "cm"
        report["world"] = "cube frame: origin at the centre of the cube's bottom face (ground plane), +z up, centimetres"
    else:
        report["scale_source"] = "none"
        report["units"] = "model units"
        report["world"] = "COLMAP model frame (arbitrary scale and orientation)"
        if not cfg.calibrate:
            log.info("--no-calibrate: the model is kept as it is")
        else:
            log.warning(
                "NO CUBE MARKERS FOUND in %s (dictionary %s): the model is NOT metric and z is not up; "
                "traits will be in model units unless the traits stage finds the cube in the point cloud",
                ws.images_dir, cube.dictionary,
            )
            report["events"].append("no markers: unscaled model")

    reg = _registered_names(rec)
    missing = [n for n in names if n not in reg]
    report["registered"] = len(reg)
    report["unregistered"] = missing
    report["mean_reprojection_error_px"] = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None
    report["num_points"] = int(rec.num_points3D())
    cam = rec.cameras[next(iter(rec.cameras))]
    report["camera"] = {"model": cam.model.name, "params": list(map(float, cam.params)), "width": cam.width, "height": cam.height}

    # outputs
    t0 = time.perf_counter()
    with colmap_logging(cfg.colmap_log):
        write_colmap(rec, ws.sparse_dir)
        write_colmap(rec, ws.sparse_text_dir, text=True)
    write_points_ply(rec, ws.sparse_points_ply)
    extra = {
        "ply_file_path": ws.sparse_points_ply.name,
        "plantsplat": {"units": report["units"], "world": report["world"], "scale_source": report["scale_source"]},
    }
    if cal is not None:
        extra["plantsplat"]["cube_from_model"] = cal.matrix().tolist()
    write_transforms(rec, ws.transforms_json, masks_dir=ws.masks_dir if ws.masks_dir.is_dir() else None, extra=extra)
    report["timings"]["write_s"] = time.perf_counter() - t0
    report["timings"]["total_s"] = time.perf_counter() - t_start
    report["timings"] = {k: round(v, 3) for k, v in report["timings"].items()}
    write_json_atomic(ws.poses_json, report)

    log.info(
        "poses: %d/%d frames registered, reprojection %s px, scale %s",
        len(reg), len(names),
        "n/a" if report["mean_reprojection_error_px"] is None else f"{report['mean_reprojection_error_px']:.2f}",
        f"from the cube ({cal.median_residual_px:.2f} px marker residual)" if cal else "NONE (model units)",
    )
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        wrong = report.get("wrongly_posed", [])
        # frames SfM registered but posed wrongly are left out without failing the capture: the rest are sound
        if len(reg) + len(wrong) < cfg.min_registered * len(names):
            found = report.get("models_found") or []
            split = (
                f"COLMAP split the capture into {len(found)} models ({', '.join(map(str, found))} frames) that could "
                "not be merged (each part must see the cube); "
                if len(found) > 1 and report.get("models_merged", 1) < len(found)
                else ""
            )
            raise PlantsplatError(
                f"{ws.images_dir}: only {len(reg)}/{len(names)} frames registered; {split}unregistered: {shown}; "
                "outputs were written for the registered frames; re-take the video more slowly or with more overlap, "
                "or try --matcher exhaustive",
                exit_code=3,
            )
        log.warning("%d frame(s) are left out (%d did not register, %d were posed wrongly): %s",
                    len(missing), len(missing) - len(wrong), len(wrong), shown)
    return report

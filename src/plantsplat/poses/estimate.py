"""The poses stage: register every frame, check the model, calibrate it with the cube, write the outputs.

:func:`estimate_poses` is the library entry point used by ``plantsplat poses`` and ``plantsplat run``.

1. The cube's markers are detected once (:mod:`plantsplat.markers`, ``WS/markers.json``).
2. Registration needs neither masks nor the cube: SIFT on whole frames, pairs chosen for orbit videos
   (:mod:`plantsplat.poses.pairs`: video neighbours and retrieval with a vocabulary learned from the
   capture; every pair when that is affordable), COLMAP's incremental mapper; frames it leaves out
   are matched again against the registered frames near them and mapping continues from the model.
3. Frames whose camera leaves the path of its video neighbours are left out
   (:func:`~plantsplat.poses.checks.off_path`).
4. The cube gives scale, gravity and origin only (:func:`~plantsplat.poses.calibrate.calibrate`),
   then a bundle adjustment holds the marker corners fixed on the cube.
5. The model is checked (:mod:`plantsplat.poses.checks`): registered share, camera path, the cube's
   reprojection, its scale from both halves of the video, the SfM points on its faces. A model that
   fails a check is not written: the stage stops with a one-line error naming the check.

Usage:
    from plantsplat.poses import PosesConfig, estimate_poses
    report = estimate_poses(Workspace("ws/plant_01"), PosesConfig())
    report["registered"], report["total"], report["scale_source"]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from plantsplat.checks import Check
from plantsplat.cube import CubeSpec
from plantsplat.errors import EXIT_POSES_FAILED, PlantsplatError, UsageError
from plantsplat.io import read_json, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.markers import Markers
from plantsplat.workspace import Workspace

log = get_logger(__name__)

MIN_FRAMES = 3
WORK_DIR = ".plantsplat/colmap"
POSES_VERSION = 2


@dataclass
class PosesConfig:
    """Options of the poses stage."""

    matcher: Literal["auto", "retrieval", "exhaustive"] = "auto"
    """Pairs to match: retrieval (video neighbours + visually similar frames), exhaustive (every pair), auto
    (exhaustive up to --exhaustive-max-frames frames, else retrieval)."""
    mapper: Literal["auto", "incremental", "global"] = "auto"
    """COLMAP mapper: incremental (frames missing at first are matched again and mapping continues), global (global
    mapping, then incremental mapping continued from it), or auto (both; the model its own matches contradict least)."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "RADIAL"
    """COLMAP camera model shared by all frames (phones: RADIAL)."""
    max_features: int = 2048
    """SIFT features per frame."""
    sift_first_octave: int = -1
    """SIFT first octave: -1 upsamples frames 2x (more small features, COLMAP's default); 0 is faster."""
    video_window: int = 3
    """Retrieval matching: each frame is matched with this many following frames of the video."""
    retrieval_neighbours: int = 20
    """Retrieval matching: each frame is matched with this many frames most alike in visual words."""
    vocabulary_words: int = 1024
    """Retrieval matching: words of the visual vocabulary learned from the capture."""
    exhaustive_max_frames: int = 50
    """With --matcher auto, captures of up to this many frames match every pair."""
    import_colmap: Path | None = None
    """Use this COLMAP model (folder with cameras/images/points3D, .bin or .txt) instead of running SfM."""
    import_transforms: Path | None = None
    """Use this nerfstudio transforms.json instead of running SfM."""
    calibrate: bool = True
    """Calibrate scale, gravity and origin with the ArUco cube (--no-calibrate keeps the model as it is)."""
    max_residual_px: float = 3.0
    """Marker detections reprojecting worse than this (pixels) are left out of the calibration; the cube check uses it."""
    cube_bundle_adjustment: bool = True
    """After calibration, bundle-adjust with the cube's marker corners as fixed control points (SfM only)."""
    min_registered: float = 0.7
    """Fail (exit code 3) when fewer than this share of the frames is registered and on the camera's path."""
    warn_registered: float = 0.95
    """Warn (the run goes on with the frames it could use) when fewer than this share is registered."""
    min_cube_frames: float = 0.1
    """Warn when the cube's markers are found in fewer than this share of the frames."""
    max_camera_cube_px: float = 15.0
    """A camera whose own marker detections the calibrated cube misses by more than this (px, RMS) is wrong: it is
    left out."""
    max_path_deviation: float = 0.3
    """A camera off the path of its video neighbours by more than this share of the step to them (or of twice
    their turn) is left out."""
    max_off_path_block: float = 0.1
    """The longest stretch of consecutive frames (share of the frames, at least 4) checked as a block that agrees with
    itself but was posed somewhere off the path of the frames around it."""
    max_scale_disagreement: float = 0.03
    """Fail when the cube's scale from the two halves of the video differs by more than this share."""
    max_face_offset_cm: float = 0.3
    """Fail when the SfM points on a face of the cube lie farther than this from the face's plane."""
    cube_size: float = CubeSpec.size
    """Cube edge (cm)."""
    marker_size: float = CubeSpec.marker_size
    """Marker side, black border included (cm)."""
    dictionary: str = "DICT_4X4_50"
    """ArUco dictionary of the cube's markers."""
    max_pair_error_px: float = 4.0
    """A matched pair whose inliers lie farther than this (median Sampson distance, px) from the epipolar geometry the
    model gives the two frames is contradicted by the model (--mapper auto keeps the model with the fewest)."""
    mapper_keep_share: float = 0.95
    """With --mapper auto, only models keeping at least this share of the most frames any mapper keeps on the cameras' path
    compete on consistency."""
    mapper_switch_sigma: float = 3.0
    """With --mapper auto, a model other than the incremental mapper's is kept only when the matched pairs the
    incremental model contradicts and it does not outnumber the reverse by this many standard deviations."""
    num_threads: int = 2
    """CPU threads of feature extraction (matching, k-means and the mappers run on one: the same frames then give the
    same cameras)."""
    seed: int = 0
    """Random seed (COLMAP's RANSAC and mapper)."""
    colmap_log: bool = False
    """Show COLMAP's own log on stderr (also on with the global --verbose)."""

    def cube(self) -> CubeSpec:
        return CubeSpec(size=self.cube_size, marker_size=self.marker_size, dictionary=self.dictionary)

    def sfm_options(self):
        from plantsplat.poses.sfm import SfmConfig

        return SfmConfig(camera_model=self.camera_model, max_features=self.max_features,
                          first_octave=self.sift_first_octave, num_threads=self.num_threads, seed=self.seed,
                          verbose=self.colmap_log)


def outputs(ws: Workspace) -> list[Path]:
    """Files the poses stage writes."""
    return [ws.sparse_dir, ws.sparse_text_dir, ws.transforms_json, ws.poses_json, ws.sparse_points_ply, ws.markers_json]


def video_times(ws: Workspace, names: list[str]) -> list[float]:
    """Each frame's time in the capture: its source frame number for a video, else its position."""
    try:
        info = read_json(ws.frames_json) if ws.frames_json.is_file() else {}
        src = {f["name"]: f["source_index"] for f in info.get("frames", [])} if info.get("kind") == "video" else {}
    except (PlantsplatError, KeyError, TypeError, AttributeError):
        src = {}
    if all(isinstance(src.get(n), int) for n in names):
        return [float(src[n]) for n in names]
    return [float(i) for i in range(len(names))]


def _registered(rec) -> dict:
    return {im.name: im for im in rec.images.values() if im.has_pose}


# --- registration --------------------------------------------------------------------------------


def _match(db: Path, work: Path, names: list[str], cfg: PosesConfig, report: dict) -> Path | None:
    """Match the chosen pairs into ``db``; returns the vocabulary file (None when every pair was matched)."""
    from plantsplat.poses import pairs as P
    from plantsplat.poses.sfm import match_exhaustive, match_pairs

    opts = cfg.sfm_options()
    exhaustive = cfg.matcher == "exhaustive" or (cfg.matcher == "auto" and len(names) <= cfg.exhaustive_max_frames)
    report["matcher"] = "exhaustive" if exhaustive else "retrieval"
    if exhaustive:
        log.info("SfM: matching every pair of %d frames", len(names))
        match_exhaustive(db, opts)
        report["pairs"] = len(names) * (len(names) - 1) // 2
        return None
    vocab = P.build_vocabulary(db, work / "vocabulary.bin", cfg.vocabulary_words, cfg.seed)
    pairs = sorted(set(P.video_pairs(names, cfg.video_window))
                   | set(P.retrieval_pairs(db, vocab, cfg.retrieval_neighbours)))
    report["pairs"] = len(pairs)
    log.info("SfM: matching %d pairs (video neighbours and retrieval)", len(pairs))
    match_pairs(db, work, pairs, opts, "main")
    return vocab


def _extend(rec, db: Path, vocab: Path | None, names: list[str], ws: Workspace, cfg: PosesConfig, report: dict):
    """Frames missing from ``rec``: matched with the registered frames near them, then mapping continues."""
    from plantsplat.poses import pairs as P
    from plantsplat.poses.sfm import incremental, match_pairs, write_model

    reg = _registered(rec)
    missing = [n for n in names if n not in reg]
    work = ws.root / WORK_DIR
    extra = set(P.pairs_for_missing(names, rec))
    if vocab is not None:
        extra |= set(P.retrieval_pairs(db, vocab, 2 * cfg.retrieval_neighbours, query=missing))
    log.info("SfM: %d frames missing: matching %d more pairs around them, continuing the model", len(missing), len(extra))
    match_pairs(db, work, sorted(extra), cfg.sfm_options(), "missing")
    write_model(rec, work / "seed", cfg.colmap_log)
    try:
        cont = incremental(db, ws.images_dir, work / "continued", cfg.sfm_options(), input_path=work / "seed")
    except Exception as exc:  # COLMAP refuses a seed it cannot extend: keep what we have
        log.debug("continued mapping failed: %s", exc)
        cont = []
    if cont and cont[0].num_reg_images() > rec.num_reg_images():
        report["events"].append(f"continued mapping registered {cont[0].num_reg_images() - rec.num_reg_images()} more frames")
        return cont[0]
    return rec


def _map(db: Path, vocab: Path | None, names: list[str], ws: Workspace, cfg: PosesConfig, report: dict, mapper: str):
    """One mapping of the matched pairs in ``db``: the mapper, pieces merged, missing frames matched again."""
    from plantsplat.poses.sfm import global_then_incremental, incremental, merge_models

    work = ws.root / WORK_DIR
    timings = report["timings"]
    t0 = time.perf_counter()
    log.info("SfM: %s mapping", mapper)
    run = global_then_incremental if mapper == "global" else incremental
    models = run(db, ws.images_dir, work / mapper, cfg.sfm_options())
    timings["map_s"] = timings.get("map_s", 0.0) + time.perf_counter() - t0
    if not models:
        return None
    report["models_found"] = [m.num_reg_images() for m in models]
    rec = models[0]
    if len(models) > 1 and rec.num_reg_images() < len(names):
        t0 = time.perf_counter()
        merged = merge_models(models, db, ws.images_dir, work / "merged", cfg.sfm_options())
        if merged is not None and merged.num_reg_images() > rec.num_reg_images():
            report["events"].append(f"{len(models)} models merged by their common frames: {merged.num_reg_images()} frames")
            rec = merged
        timings["merge_s"] = timings.get("merge_s", 0.0) + time.perf_counter() - t0
    if mapper == "incremental" and rec.num_reg_images() < len(names):
        t0 = time.perf_counter()
        rec = _extend(rec, db, vocab, names, ws, cfg, report)
        timings["extend_s"] = timings.get("extend_s", 0.0) + time.perf_counter() - t0
    return rec


def _fewer_contradictions(errors: dict, other: dict, max_px: float) -> float:
    """How many standard deviations fewer matched pairs model ``other`` contradicts than model ``errors`` (McNemar's
    test on the pairs exactly one of them contradicts; :func:`plantsplat.poses.consistency.pair_errors`)."""
    from plantsplat.poses.consistency import contradicted

    a, b = set(contradicted(errors, max_px)), set(contradicted(other, max_px))
    only_a, only_b = len(a - b), len(b - a)
    return (only_a - only_b) / max(np.sqrt(only_a + only_b), 1.0)


def _most_consistent(db: Path, vocab: Path | None, names: list[str], times: list[float], ws: Workspace,
                     cfg: PosesConfig, report: dict):
    """Each mapper of ``cfg.mapper`` (``auto``: incremental, then global). Among the models that keep nearly as many
    frames on the cameras' path (:func:`off_path_frames`) as the best, the first, unless another contradicts
    significantly fewer of the matched pairs (:func:`_fewer_contradictions`, :mod:`plantsplat.poses.consistency`).
    The kept model's frames off the path are left out (:func:`leave_out_off_path`)."""
    from plantsplat.poses.consistency import contradiction, pair_errors

    mappers = ["incremental", "global"] if cfg.mapper == "auto" else [cfg.mapper]
    found, off = {}, {}
    for m in mappers:
        rec = _map(db, vocab, names, ws, cfg, report, m)
        if rec is not None:
            off[m] = off_path_frames(rec, names, times, cfg)
            found[m] = (rec, pair_errors(rec, db), rec.num_reg_images() - len(off[m]))
    if not found:
        return None
    most = max(k for _, _, k in found.values())
    able = [m for m in found if found[m][2] >= cfg.mapper_keep_share * most]
    z = {m: _fewer_contradictions(found[able[0]][1], found[m][1], cfg.max_pair_error_px) for m in able}
    best = max(able, key=lambda m: z[m]) if max(z.values()) > cfg.mapper_switch_sigma else able[0]
    report["mappers"] = {m: {"registered": r.num_reg_images(), "on_path": k,
                             "fewer_contradicted_sigma": round(z[m], 2) if m in z else None,
                             "contradicted_share": round(contradiction(e, cfg.max_pair_error_px), 4)}
                         for m, (r, e, k) in found.items()}
    report["mapper"] = best
    if len(found) > 1:
        report["events"].append(f"{best} mapping kept" + (": its matches contradict it least" if best != mappers[0] else ""))
    leave_out_off_path(found[best][0], names, times, cfg, report, off[best])
    return found[best][0]


def register(ws: Workspace, names: list[str], times: list[float], cfg: PosesConfig, report: dict):
    """SfM on whole frames (no masks, no cube); returns the model (model frame) :func:`_most_consistent` keeps, its
    frames off the camera's path (``times``: the frames' times in the video) left out."""
    from plantsplat.poses.sfm import extract_features

    work = ws.root / WORK_DIR
    timings = report["timings"]
    t0 = time.perf_counter()
    log.info("SfM: extracting SIFT features from %d frames", len(names))
    db = extract_features(ws.images_dir, names, work, cfg.sfm_options())
    timings["extract_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vocab = _match(db, work, names, cfg, report)
    timings["match_s"] = time.perf_counter() - t0
    rec = _most_consistent(db, vocab, names, times, ws, cfg, report)
    if rec is None:
        raise PlantsplatError(
            f"{ws.images_dir}: COLMAP could not reconstruct any model from {len(names)} frames; the frames may be "
            "too blurry, too few or too far apart (keep 6-12 degrees between neighbours)", exit_code=EXIT_POSES_FAILED)
    return rec


def _import(ws: Workspace, names: list[str], cfg: PosesConfig, report: dict):
    """The user's COLMAP model or transforms.json, renamed onto the workspace's frames."""
    from plantsplat.poses.imports import name_map, rename_images
    from plantsplat.poses.interop import read_colmap, read_transforms
    from plantsplat.poses.sfm import colmap_logging

    src = Path(cfg.import_colmap or cfg.import_transforms)
    if cfg.import_colmap is not None:
        with colmap_logging(cfg.colmap_log):
            raw = read_colmap(src)
        report["source"] = f"colmap:{src}"
    else:
        raw = read_transforms(src, None)
        report["source"] = f"transforms:{src}"
    mapping = name_map(ws, [im.name for im in raw.images.values() if im.has_pose], names)
    if not mapping:
        raise PlantsplatError(f"{src}: none of its images matches a frame in {ws.images_dir} (by name or frames.json "
                              "source name); import a model of these frames")
    if cfg.import_colmap is not None and len(mapping) == raw.num_reg_images() and all(k == v for k, v in mapping.items()):
        rec = raw
    else:
        rec = rename_images(raw, mapping)
        if raw.num_points3D():
            report["events"].append("imported points dropped (image names were remapped); no sparse points")
    report["matcher"] = report["mapper"] = "import"
    report["models_found"] = [rec.num_reg_images()]
    return rec


# --- checks and calibration ---------------------------------------------------------------------


def off_path_frames(rec, names: list[str], times: list[float], cfg: PosesConfig) -> list[str]:
    """The registered frames whose camera looks away from what the cameras circle or leaves the path of its video
    neighbours, alone or as a block (:mod:`plantsplat.poses.checks`)."""
    from plantsplat.poses.checks import facing_away, off_path, off_path_runs
    from plantsplat.poses.interop import c2w_opencv

    c2w = {n: c2w_opencv(im) for n, im in _registered(rec).items()}
    drop = facing_away(c2w)
    drop += off_path({n: M for n, M in c2w.items() if n not in drop}, names, times, cfg.max_path_deviation)
    drop += off_path_runs({n: M for n, M in c2w.items() if n not in drop}, names, times, cfg.max_path_deviation,
                          max_run=max(4, round(cfg.max_off_path_block * len(names))))
    return drop


def leave_out_off_path(rec, names: list[str], times: list[float], cfg: PosesConfig, report: dict,
                       drop: list[str] | None = None) -> list[str]:
    """Deregister the frames :func:`off_path_frames` finds (``drop``: already found for this model); returns their
    names."""
    reg = _registered(rec)
    drop = off_path_frames(rec, names, times, cfg) if drop is None else drop
    for n in drop:
        rec.deregister_frame(reg[n].frame_id)
    if drop:
        shown = ", ".join(drop[:10]) + (f" and {len(drop) - 10} more" if len(drop) > 10 else "")
        log.warning("%d frame(s) left out: their cameras leave the path of their video neighbours (%s)", len(drop), shown)
        report["events"].append(f"{len(drop)} frame(s) off the camera's path left out")
    report["off_path"] = sorted(set(report.get("off_path", [])) | set(drop))
    return drop


def _composed(new, old):
    """Calibration ``new`` (found in the frame ``old`` maps into) made to map the original model frame."""
    m = new.matrix() @ old.matrix()
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    new.scale, new.R, new.t = s, m[:3, :3] / s, m[:3, 3]
    return new


def _second_chance(rec, ws: Workspace, names: list[str], times: list[float], cfg: PosesConfig, report: dict) -> None:
    """Frames left out so far, localised against the model's points (:mod:`plantsplat.poses.localize`); those
    whose camera then lies on the path of its video neighbours stay."""
    from plantsplat.poses.localize import add_frames, localize_frames

    missing = [n for n in names if n not in _registered(rec)]
    if not missing or not rec.num_points3D():
        return
    t0 = time.perf_counter()
    added = add_frames(rec, ws.root / WORK_DIR / "database.db", localize_frames(rec, ws.root / WORK_DIR / "database.db",
                                                                                missing))
    before = set(report.get("off_path", []))
    dropped = set(leave_out_off_path(rec, names, times, cfg, report)) if added else set()
    report["off_path"] = sorted(before | (dropped - set(added)))
    kept = [n for n in added if n not in dropped]
    report["localized"] = kept
    report["timings"]["localize_s"] = time.perf_counter() - t0
    if kept:
        report["events"].append(f"{len(kept)} frame(s) left out at first localised against the model")


def _leave_out_cube_misses(rec, cal, cfg: PosesConfig, report: dict) -> None:
    """Deregister the cameras whose every marker detection the calibrated cube misses by more than
    ``cfg.max_camera_cube_px``: the cube stands where most frames see it, so these cameras are misplaced."""
    kept = set(cal.frame_residuals_px)
    worst: dict[str, float] = {}
    for name, _, rms in cal.detections_rejected:
        if name not in kept:
            worst[name] = min(worst.get(name, np.inf), rms)
    drop = sorted(n for n, e in worst.items() if e > cfg.max_camera_cube_px)
    reg = _registered(rec)
    for n in drop:
        if n in reg:
            rec.deregister_frame(reg[n].frame_id)
    if drop:
        log.warning("%d frame(s) left out: the cube reprojects far from their own markers (%s)", len(drop), ", ".join(drop[:10]))
        report["events"].append(f"{len(drop)} frame(s) whose markers the cube misses left out")
    report["cube_misses"] = drop


def calibrate_model(rec, markers: Markers, cube: CubeSpec, cfg: PosesConfig, sfm: bool, report: dict,
                    order: list[str] | None = None):
    """Move ``rec`` into the cube frame (cm, z up); with ``sfm``, bundle-adjust on the cube's corners. Returns the
    calibration (None without markers). ``order``: the frames in video order, for the scale's uncertainty."""
    from plantsplat.poses.calibrate import calibrate, refine_with_cube, scale_uncertainty
    from plantsplat.poses.sfm import MAP_THREADS, colmap_logging

    det = markers.frames
    cal = calibrate(rec, det, cube, cfg.max_residual_px) if det else None
    if cal is None:
        return None
    rec.transform(cal.to_pycolmap())
    if sfm:
        _leave_out_cube_misses(rec, cal, cfg, report)
    report["scale_uncertainty"] = scale_uncertainty(rec, det, order or sorted(det), cube, cfg.max_residual_px)
    if sfm and cfg.cube_bundle_adjustment and cal.consistent:
        t0 = time.perf_counter()
        with colmap_logging(cfg.colmap_log):
            n_ctrl = refine_with_cube(rec, det, cal, cube, MAP_THREADS)
        if n_ctrl:
            cal2 = calibrate(rec, det, cube, cfg.max_residual_px)
            if cal2 is not None and cal2.consistent:
                report["scale_uncertainty"]["bundle_adjustment_change"] = float(np.log(cal2.scale))
                rec.transform(cal2.to_pycolmap())  # a small correction: the control points fix the frame
                cal = _composed(cal2, cal)
            report["events"].append(f"bundle adjustment with {n_ctrl} cube corners as control points")
        report["timings"]["cube_ba_s"] = time.perf_counter() - t0
    return cal


def cube_checks(rec, cal, markers: Markers, cube: CubeSpec, times: dict[str, float], cfg: PosesConfig) -> list[Check]:
    """The cube's checks of a calibrated model: reprojection, scale from both halves of the video, faces' planes."""
    from plantsplat.poses.calibrate import calibrate
    from plantsplat.poses.checks import face_offsets

    out = [Check("cube_reprojection_px", cal.median_residual_px, cfg.max_residual_px, "<=",
                 f"median over {cal.frames_with_markers} frames with markers"),
           Check("cube_detections_kept", cal.inlier_ratio, 0.5, ">=", "share of marker detections within the limit")]
    seen = sorted((n for n in markers.frames if n in times), key=times.get)
    halves = [dict((n, markers.frames[n]) for n in part) for part in (seen[: len(seen) // 2], seen[len(seen) // 2:])]
    cals = [calibrate(rec, h, cube, cfg.max_residual_px) if len(h) >= 2 else None for h in halves]
    if all(c is not None for c in cals):
        rel = abs(np.log(cals[0].scale / cals[1].scale))
        out.append(Check("cube_scale_halves", float(rel), cfg.max_scale_disagreement, "<=",
                         "relative difference of the cube's scale from the first and second half of the video"))
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    faces = face_offsets(pts, cube)
    if faces:
        worst = max(faces, key=lambda f: abs(faces[f][0]))
        out.append(Check("cube_face_offset_cm", abs(faces[worst][0]), cfg.max_face_offset_cm, "<=",
                         f"SfM points on the cube's {worst} face (of {len(faces)} faces seen)"))
    return out


def model_checks(rec, cal, markers: Markers, cube: CubeSpec, names: list[str], times: list[float],
                 cfg: PosesConfig) -> list[Check]:
    """Every check of the final model (see :mod:`plantsplat.poses.checks`)."""
    reg = len(_registered(rec))
    checks = [Check("registered_share", reg / len(names), cfg.min_registered, ">=",
                    f"{reg} of {len(names)} frames registered and on the camera's path"),
              Check("registered_share_all", reg / len(names), cfg.warn_registered, ">=",
                    f"{len(names) - reg} frame(s) left out; the later stages use the {reg} others", severity="warn")]
    if cal is not None:
        checks += cube_checks(rec, cal, markers, cube, dict(zip(names, times)), cfg)
        seen = len(markers.frames)
        checks.append(Check("cube_frames_share", seen / len(names), cfg.min_cube_frames, ">=",
                            f"the cube's markers were found in {seen} of {len(names)} frames; a scale to trust needs "
                            "them seen from several sides", severity="warn"))
    return checks


def _describe(report: dict, rec, cal, cfg: PosesConfig, names: list[str]) -> None:
    """The report's calibration, registration and camera entries."""
    from plantsplat.poses.calibrate import up_vector

    if cal is not None:
        report.update(scale_source="aruco", similarity=cal.summary(), up_vector_model=up_vector(cal),
                      marker_residuals_px=cal.frame_residuals_px, units="cm",
                      cube={"size_cm": cfg.cube_size, "marker_size_cm": cfg.marker_size, "dictionary": cfg.dictionary},
                      world="cube frame: origin at the centre of the cube's bottom face (ground plane), +z up, centimetres")
    else:
        report.update(scale_source="none", units="model units", world="COLMAP model frame (arbitrary scale and orientation)")
    reg = _registered(rec)
    report["registered"] = len(reg)
    report["unregistered"] = [n for n in names if n not in reg]
    report["mean_reprojection_error_px"] = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None
    report["num_points"] = int(rec.num_points3D())
    cam = rec.cameras[next(iter(rec.cameras))]
    report["camera"] = {"model": cam.model.name, "params": list(map(float, cam.params)), "width": cam.width,
                        "height": cam.height}


def _write_outputs(ws: Workspace, rec, cal, report: dict, cfg: PosesConfig) -> None:
    from plantsplat.poses.interop import (
        write_colmap,
        write_points_ply,
        write_transforms,
    )
    from plantsplat.poses.sfm import colmap_logging

    with colmap_logging(cfg.colmap_log):
        write_colmap(rec, ws.sparse_dir)
        write_colmap(rec, ws.sparse_text_dir, text=True)
    write_points_ply(rec, ws.sparse_points_ply)
    extra = {"ply_file_path": ws.sparse_points_ply.name,
             "plantsplat": {"units": report["units"], "world": report["world"], "scale_source": report["scale_source"]}}
    if cal is not None:
        extra["plantsplat"]["cube_from_model"] = cal.matrix().tolist()
    write_transforms(rec, ws.transforms_json, mask_prefix=ws.masks_dir.name, extra=extra)


def _markers(ws: Workspace, names: list[str], cube: CubeSpec, cfg: PosesConfig, report: dict) -> Markers:
    from plantsplat.markers import detect_frames, write_markers

    t0 = time.perf_counter()
    markers = detect_frames(ws.images_dir, names, cube) if cfg.calibrate else Markers(names=list(names))
    write_markers(ws.markers_json, markers, cube)
    report["timings"]["detect_markers_s"] = time.perf_counter() - t0
    report["frames_with_markers"] = len(markers.frames)
    report["marker_edge_shift_px"] = markers.edge_shift_px
    return markers


def _fail(ws: Workspace, rec, report: dict, failed: list[Check], cfg: PosesConfig) -> PlantsplatError:
    """Record a model that failed its checks (kept aside for inspection, not written as the output)."""
    from plantsplat.poses.interop import write_colmap
    from plantsplat.poses.sfm import colmap_logging

    rejected = ws.root / WORK_DIR / "rejected"
    with colmap_logging(cfg.colmap_log):
        write_colmap(rec, rejected)
    report["status"] = "failed"
    report["rejected_model"] = str(rejected)
    write_json_atomic(ws.poses_json, report)
    what = "; ".join(c.line() for c in failed)
    return PlantsplatError(
        f"{ws.images_dir}: the camera model fails its checks ({what}); nothing was written as poses (the model is kept "
        f"in {rejected} for inspection). Re-take the video more slowly with more overlap, or try --matcher exhaustive",
        exit_code=EXIT_POSES_FAILED)


def estimate_poses(ws: Workspace | str | Path, cfg: PosesConfig | None = None) -> dict:
    """Run the poses stage on workspace ``ws``; returns the ``poses.json`` report.

    Raises :class:`PlantsplatError` on bad input (too few frames, broken import) and, with exit code 3,
    when the model fails its checks. Whether the stage needs to run at all is decided by
    :func:`plantsplat.pipeline.poses_stage`.
    """
    from plantsplat.poses.sfm import n_threads_env

    cfg = cfg or PosesConfig()
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    if cfg.import_colmap is not None and cfg.import_transforms is not None:
        raise UsageError("pass only one of --import-colmap and --import-transforms")
    ws.require(ws.images_dir, "frames")
    names = ws.image_names()
    if len(names) < MIN_FRAMES:
        raise PlantsplatError(f"{ws.images_dir}: only {len(names)} frame(s); structure from motion needs at least "
                              f"{MIN_FRAMES} (the paper uses 100-150); run `plantsplat frames` with more frames")
    n_threads_env(cfg.num_threads)
    cube = cfg.cube()
    t_start = time.perf_counter()
    report: dict = {"version": POSES_VERSION, "total": len(names), "timings": {}, "events": [],
                    "camera_model": cfg.camera_model, "source": "sfm"}
    markers = _markers(ws, names, cube, cfg, report)
    sfm = cfg.import_colmap is None and cfg.import_transforms is None
    times = video_times(ws, names)
    rec = register(ws, names, times, cfg, report) if sfm else _import(ws, names, cfg, report)
    t0 = time.perf_counter()
    cal = calibrate_model(rec, markers, cube, cfg, sfm, report, [n for _, n in sorted(zip(times, names))])
    report["timings"]["calibrate_s"] = time.perf_counter() - t0
    if sfm and cal is not None:  # the cube's bundle adjustment moves weakly held cameras: judge the path again
        leave_out_off_path(rec, names, times, cfg, report)
    if sfm:
        _second_chance(rec, ws, names, times, cfg, report)
    if cal is None and cfg.calibrate:
        log.warning("NO CUBE MARKERS FOUND in %s (dictionary %s): the model is NOT metric and z is not up; traits will "
                    "be in model units unless the traits stage finds the cube in the point cloud", ws.images_dir,
                    cube.dictionary)
        report["events"].append("no markers: unscaled model")
    checks = model_checks(rec, cal, markers, cube, names, times, cfg)
    report["checks"] = [c.as_dict() for c in checks]
    _describe(report, rec, cal, cfg, names)
    report["timings"]["total_s"] = time.perf_counter() - t_start
    report["timings"] = {k: round(v, 3) for k, v in report["timings"].items()}
    failed = [c for c in checks if not c.passed and c.severity == "fail"]
    if failed:
        raise _fail(ws, rec, report, failed, cfg)
    warned = [c for c in checks if not c.passed]
    report["status"] = "warning" if warned else "ok"
    for c in warned:
        log.warning("poses: %s", c.line())
    _write_outputs(ws, rec, cal, report, cfg)
    write_json_atomic(ws.poses_json, report)
    log.info("poses: %d/%d frames registered, reprojection %s px, scale %s", report["registered"], len(names),
             "n/a" if report["mean_reprojection_error_px"] is None else f"{report['mean_reprojection_error_px']:.2f}",
             f"from the cube ({cal.median_residual_px:.2f} px marker residual)" if cal else "NONE (model units)")
    if report["unregistered"]:
        log.warning("%d frame(s) are left out: %s", len(report["unregistered"]), ", ".join(report["unregistered"][:10]))
    return report

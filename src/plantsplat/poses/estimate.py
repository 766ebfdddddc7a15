"""Registration, the model's checks and the cube's calibration of the poses stage (:mod:`plantsplat.poses.stage`
runs them over a workspace).

1. Registration needs neither masks nor the cube (:func:`register`): SIFT on whole frames, pairs chosen for orbit
   videos (:mod:`plantsplat.poses.pairs`: video neighbours and retrieval with a vocabulary learned from the
   capture; every pair when that is affordable), COLMAP's incremental mapper; frames it leaves out are matched
   again against the registered frames near them and mapping continues from the model. The kept model's points
   are then triangulated again from every verified match, with its cameras as they are at the end, and
   bundle-adjusted; frames still left out (by the mappers or the path check of step 2) are localised against it
   round by round, the points made again after each (:func:`localize_in_rounds`). Last, the verified pairs of the
   frames the model holds weakly are matched again, guided by their geometry, the points made again from them, and
   those the weak frames share with one other frame only left out (:mod:`plantsplat.poses.guided`). A user's model
   is imported instead by :func:`import_model`.
2. Frames whose camera leaves the path of its video neighbours are left out (:func:`leave_out_off_path`,
   :func:`plantsplat.poses.checks.off_path`).
3. The cube gives scale, gravity and origin only (:func:`calibrate_model`,
   :func:`plantsplat.poses.calibrate.calibrate`), then a bundle adjustment holds the marker corners fixed on the cube.
4. The model is checked (:func:`model_checks`, :mod:`plantsplat.poses.checks`): registered share, camera path, the
   cube's reprojection, its scale from both halves of the video, the SfM points on its faces.

Usage:
    rec = register(ws, names, times, PosesConfig(), report)
    cal = calibrate_model(rec, markers, cube, cfg, True, report)
    checks = model_checks(rec, cal, markers, cube, names, times, cfg)
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from plantsplat.checks import Check
from plantsplat.cube import CubeSpec
from plantsplat.errors import EXIT_POSES_FAILED, PlantsplatError
from plantsplat.io import read_image
from plantsplat.log import get_logger
from plantsplat.markers import Markers
from plantsplat.poses.calibrate import calibrate, refine_with_cube, scale_uncertainty
from plantsplat.poses.checks import face_offsets, facing_away, off_path, off_path_runs
from plantsplat.poses.config import GUIDED_DATABASE, LOGGED_NAMES, WORK_DIR, PosesConfig
from plantsplat.poses.consistency import contradicted, contradiction, pair_errors
from plantsplat.poses.guided import drop_weak_two_view, pair_inliers, rematch_guided, verified_pairs_with, weakly_held
from plantsplat.poses.imports import name_map, rename_images
from plantsplat.poses.interop import c2w_opencv, read_colmap, read_transforms, registered_images
from plantsplat.poses.localize import add_frames, localize_frames
from plantsplat.poses.pairs import build_vocabulary, pairs_for_missing, retrieval_pairs, video_pairs
from plantsplat.poses.sfm import (
    MAP_THREADS,
    RETRIANGULATED_BA_ITERATIONS,
    ROUND_BA_ITERATIONS,
    colmap_logging,
    extract_features,
    extracted_names,
    finish_global_mapping,
    finish_matching,
    global_then_incremental,
    incremental,
    match_exhaustive,
    match_pairs,
    merge_models,
    retriangulate,
    start_global_mapping,
    start_matching,
    stop_matching,
    write_model,
)
from plantsplat.workers import stop_worker
from plantsplat.workspace import Workspace

log = get_logger(__name__)


def shown_names(names: list[str]) -> str:
    """The first frame names for a log message, and how many more there are."""
    more = len(names) - LOGGED_NAMES
    return ", ".join(names[:LOGGED_NAMES]) + (f" and {more} more" if more > 0 else "")


# --- registration --------------------------------------------------------------------------------


def _match(db: Path, work: Path, names: list[str], cfg: PosesConfig, report: dict) -> Path | None:
    """Match the chosen pairs into ``db``; returns the vocabulary file (None when every pair was matched)."""
    opts = cfg.sfm_options()
    exhaustive = cfg.matcher == "exhaustive" or (cfg.matcher == "auto" and len(names) <= cfg.exhaustive_max_frames)
    report["matcher"] = "exhaustive" if exhaustive else "retrieval"
    if exhaustive:
        log.info("SfM: matching every pair of %d frames", len(names))
        match_exhaustive(db, opts)
        report["pairs"] = len(names) * (len(names) - 1) // 2
        return None
    video = sorted({tuple(sorted(p)) for p in video_pairs(names, cfg.video_window)})  # as retrieval names them
    log.info("SfM: matching %d pairs of video neighbours while a vocabulary is learned", len(video))
    early = start_matching(db, work, video, opts, "video", 1 if opts.num_threads > 1 else 0)
    try:  # learning the vocabulary and retrieval take one core: the video neighbours are matched on the other
        vocab = build_vocabulary(db, work / "vocabulary.bin", cfg.vocabulary_words, cfg.seed)
        retrieved = sorted(set(retrieval_pairs(db, vocab, cfg.retrieval_neighbours)) - set(video))
        report["pairs"] = len(video) + len(retrieved)
        log.info("SfM: matching %d more pairs (retrieval)", len(retrieved))
        match_pairs(db, work, retrieved, opts, "main")
    except BaseException:
        stop_matching(early)
        raise
    finish_matching(early)
    return vocab


def _extend(rec, db: Path, vocab: Path | None, names: list[str], ws: Workspace, cfg: PosesConfig, report: dict):
    """Frames missing from ``rec``: matched with the registered frames near them, then mapping continues."""
    reg = registered_images(rec)
    missing = [n for n in names if n not in reg]
    work = ws.root / WORK_DIR
    extra = set(pairs_for_missing(names, rec, cfg.missing_pair_neighbours))
    if vocab is not None:
        extra |= set(retrieval_pairs(db, vocab, 2 * cfg.retrieval_neighbours, query=missing))
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


def _mapped(db: Path, ws: Workspace, cfg: PosesConfig, mappers: list[str], report: dict) -> dict[str, list]:
    """Each mapper's models of the pairs matched so far (largest first). With both mappers and more than one thread,
    the global mapping runs in a process of its own beside the incremental one (:func:`start_global_mapping`);
    otherwise it runs first, so that it maps the same matches either way."""
    work = ws.root / WORK_DIR
    opts = cfg.sfm_options()
    t0 = time.perf_counter()
    apart = "global" in mappers and "incremental" in mappers and cfg.num_threads > 1
    log.info("SfM: %s mapping%s", " and ".join(mappers), " side by side" if apart else "")
    background = start_global_mapping(db, ws.images_dir, work / "global", opts) if apart else None
    models: dict[str, list] = {}
    try:
        if "global" in mappers and not apart:
            models["global"] = global_then_incremental(db, ws.images_dir, work / "global", opts)
        if "incremental" in mappers:
            models["incremental"] = incremental(db, ws.images_dir, work / "incremental", opts)
        if background is not None:
            models["global"] = finish_global_mapping(background, work / "global")
    finally:
        stop_worker(background)  # an error or Ctrl-C here: the process goes too
    report["timings"]["map_s"] = report["timings"].get("map_s", 0.0) + time.perf_counter() - t0
    return models


def _map(models: list, db: Path, vocab: Path | None, names: list[str], ws: Workspace, cfg: PosesConfig, report: dict,
         mapper: str):
    """One mapper's model from its ``models``: pieces merged, missing frames matched again (incremental)."""
    work = ws.root / WORK_DIR
    timings = report["timings"]
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
    a, b = set(contradicted(errors, max_px)), set(contradicted(other, max_px))
    only_a, only_b = len(a - b), len(b - a)
    return (only_a - only_b) / max(np.sqrt(only_a + only_b), 1.0)


def _most_consistent(db: Path, vocab: Path | None, names: list[str], times: list[float], ws: Workspace,
                     cfg: PosesConfig, report: dict):
    """Each mapper of ``cfg.mapper`` (``auto``: incremental, then global). Among the models that keep nearly as many
    frames on the cameras' path (:func:`off_path_frames`) as the best, the first, unless another contradicts
    significantly fewer of the matched pairs (:func:`_fewer_contradictions`, :mod:`plantsplat.poses.consistency`).
    The kept model's frames off the path are left out (:func:`leave_out_off_path`)."""
    mappers = ["incremental", "global"] if cfg.mapper == "auto" else [cfg.mapper]
    mapped = _mapped(db, ws, cfg, mappers, report)
    found, off = {}, {}
    for m in mappers:
        rec = _map(mapped[m], db, vocab, names, ws, cfg, report, m)
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
    frames off the camera's path (``times``: the frames' times in the video) left out, its points made again, and the
    frames left out localised against it (:func:`localize_in_rounds`)."""
    work = ws.root / WORK_DIR
    timings = report["timings"]
    t0 = time.perf_counter()
    log.info("SfM: extracting SIFT features from %d frames", len(names))
    db = extract_features(ws.images_dir, names, work, cfg.sfm_options())
    timings["extract_s"] = time.perf_counter() - t0
    extracted = extracted_names(db)
    for name in (n for n in names if n not in extracted):  # a broken frame: its own one-line error now, not at the end
        read_image(ws.images_dir / name, mode="gray")
    t0 = time.perf_counter()
    vocab = _match(db, work, names, cfg, report)
    timings["match_s"] = time.perf_counter() - t0
    rec = _most_consistent(db, vocab, names, times, ws, cfg, report)
    if rec is None:
        raise PlantsplatError(
            f"{ws.images_dir}: COLMAP could not reconstruct any model from {len(names)} frames; the frames may be "
            "too blurry, too few or too far apart (keep 6-12 degrees between neighbours)", exit_code=EXIT_POSES_FAILED)
    t0 = time.perf_counter()
    rec = _triangulated_again(rec, db, ws, cfg)
    timings["retriangulate_s"] = time.perf_counter() - t0
    rec = localize_in_rounds(rec, db, ws, names, times, cfg, report)
    t0 = time.perf_counter()
    rec = _weak_frames_guided(rec, db, ws, names, cfg, report)
    timings["guided_s"] = time.perf_counter() - t0
    return rec


def _weak_frames_guided(rec, db: Path, ws: Workspace, names: list[str], cfg: PosesConfig, report: dict):
    """``rec`` with its points made again (:func:`_triangulated_again`) from a copy of ``db`` in which the verified pairs
    of the frames it holds weakly are matched again, guided (:mod:`plantsplat.poses.guided`; ``poses.json``:
    ``guided``), less the points the weak frames share with one other frame only (:func:`drop_weak_two_view`). Which
    frames are registered is decided before, from ``db``'s own matches; the copy only makes points. ``rec`` as it is
    when no frame is weakly held."""
    if cfg.weak_frame_share <= 0:
        return rec
    weak = weakly_held(rec, names, cfg.weak_frame_share)
    pairs = verified_pairs_with(db, weak)
    if not pairs:
        return rec
    guided_db = ws.root / WORK_DIR / GUIDED_DATABASE
    rematch_guided(db, guided_db, ws.root / WORK_DIR, pairs, cfg.sfm_options())
    before, after = pair_inliers(db, pairs), pair_inliers(guided_db, pairs)
    rec = _triangulated_again(rec, guided_db, ws, cfg)
    dropped = drop_weak_two_view(rec, weak)
    report["guided"] = {"frames": weak, "pairs": len(pairs), "inliers_before": before, "inliers_after": after,
                        "two_view_points_dropped": dropped}
    log.info("SfM: %d weakly held frame(s): %d of their verified pairs matched again, guided (%d -> %d inliers; "
             "%d two-view points through them left out)", len(weak), len(pairs), before, after, dropped)
    return rec


def _triangulated_again(rec, db: Path, ws: Workspace, cfg: PosesConfig, iterations: int = RETRIANGULATED_BA_ITERATIONS):
    """``rec``'s cameras with every verified match triangulated again, then bundle-adjusted (points, cameras, focal
    length and distortion; at most ``iterations``).

    Incremental mapping makes each point from the cameras as they were when the point was made, and the pieces
    of a merge or of continued mapping were made apart; made again from the final cameras and every match, the
    points hold each camera by all it sees (docs/stages/poses.md has the measured effect)."""
    poses = {im.name: im.cam_from_world() for im in rec.images.values() if im.has_pose}
    return retriangulate(rec, poses, db, ws.images_dir, ws.root / WORK_DIR / "retriangulated", cfg.sfm_options(),
                         iterations)


def import_model(ws: Workspace, names: list[str], cfg: PosesConfig, report: dict):
    """The user's COLMAP model or transforms.json, renamed onto the workspace's frames."""
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
    c2w = {n: c2w_opencv(im) for n, im in registered_images(rec).items()}
    drop = facing_away(c2w, cfg.max_facing_away_deg)
    drop += off_path({n: M for n, M in c2w.items() if n not in drop}, names, times, cfg.max_path_deviation,
                     cfg.max_off_path_share)
    drop += off_path_runs({n: M for n, M in c2w.items() if n not in drop}, names, times, cfg.max_path_deviation,
                          max_run=max(4, round(cfg.max_off_path_block * len(names))))
    return drop


def _deregister(rec, names) -> None:
    """Take the frames ``names`` out of ``rec`` (those it has registered)."""
    reg = registered_images(rec)
    for n in names:
        if n in reg:
            rec.deregister_frame(reg[n].frame_id)


def leave_out_off_path(rec, names: list[str], times: list[float], cfg: PosesConfig, report: dict,
                       drop: list[str] | None = None) -> list[str]:
    """Deregister the frames :func:`off_path_frames` finds (``drop``: already found for this model); returns their
    names."""
    drop = off_path_frames(rec, names, times, cfg) if drop is None else drop
    _deregister(rec, drop)
    if drop:
        log.warning("%d frame(s) left out: their cameras leave the path of their video neighbours (%s)", len(drop),
                    shown_names(drop))
        report["events"].append(f"{len(drop)} frame(s) off the camera's path left out")
    report["off_path"] = sorted(set(report.get("off_path", [])) | set(drop))
    return drop


def _composed(new, old):
    """Calibration ``new`` (found in the frame ``old`` maps into) made to map the original model frame."""
    m = new.matrix() @ old.matrix()
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    new.scale, new.R, new.t = s, m[:3, :3] / s, m[:3, 3]
    return new


def _localized_on_path(rec, db: Path, names: list[str], times: list[float], cfg: PosesConfig) -> list[str]:
    """The frames missing from ``rec`` localised against its points (:mod:`plantsplat.poses.localize`) and added,
    those whose camera then leaves the path of its video neighbours taken out again; returns the names kept."""
    missing = [n for n in names if n not in registered_images(rec)]
    if not missing or not rec.num_points3D():
        return []
    added = add_frames(rec, db, localize_frames(rec, db, missing, cfg.sfm_options().min_pose_inliers))
    if not added:
        return []
    off = set(off_path_frames(rec, names, times, cfg)) & set(added)
    _deregister(rec, off)
    return [n for n in added if n not in off]


def _record_localized(report: dict, kept: list[str], event: str) -> None:
    """``kept`` in ``poses.json``: among the frames localised, no longer among those off the path."""
    report["localized"] = sorted(set(report.get("localized", [])) | set(kept))
    report["off_path"] = sorted(set(report.get("off_path", [])) - set(kept))
    if kept:
        report["events"].append(event)


def localize_in_rounds(rec, db: Path, ws: Workspace, names: list[str], times: list[float], cfg: PosesConfig,
                       report: dict):
    """The frames the mappers or the path check left out, localised against the model round by round
    (:func:`_localized_on_path`): after each round that keeps frames, the points are triangulated again with them
    (:func:`_triangulated_again`), so that the next round can localise the frames that see only theirs; until a round
    keeps none. A stretch the mapper posed as a block on the far side of the orbit (left out by the path check)
    comes back so from both its ends, its frames held by points of their own. Returns the model."""
    t0 = time.perf_counter()
    kept: list[str] = []
    rounds = 0
    while more := _localized_on_path(rec, db, names, times, cfg):
        kept += more
        rounds += 1
        rec = _triangulated_again(rec, db, ws, cfg, ROUND_BA_ITERATIONS)
    if kept:
        log.info("SfM: %d frame(s) left out by mapping localised against the model in %d round(s)", len(kept), rounds)
    _record_localized(report, kept, f"{len(kept)} frame(s) left out by mapping localised against the model in "
                                    f"{rounds} round(s), their points triangulated")
    report["timings"]["localize_rounds_s"] = time.perf_counter() - t0
    return rec


def localize_left_out(rec, ws: Workspace, names: list[str], times: list[float], cfg: PosesConfig, report: dict) -> None:
    """Frames left out after the calibration (the cube's checks, the path judged again), localised against the
    calibrated model's points; those whose camera lies on the path of its video neighbours stay, without points of
    their own (the model's points are final)."""
    t0 = time.perf_counter()
    kept = _localized_on_path(rec, ws.root / WORK_DIR / "database.db", names, times, cfg)
    _record_localized(report, kept, f"{len(kept)} frame(s) left out at first localised against the model")
    report["timings"]["localize_s"] = time.perf_counter() - t0


def _leave_out_cube_misses(rec, cal, cfg: PosesConfig, report: dict) -> None:
    """Deregister the cameras whose every marker detection the calibrated cube misses by more than
    ``cfg.max_camera_cube_px``: the cube stands where most frames see it, so these cameras are misplaced."""
    kept = set(cal.frame_residuals_px)
    worst: dict[str, float] = {}
    for name, _, rms in cal.detections_rejected:
        if name not in kept:
            worst[name] = min(worst.get(name, np.inf), rms)
    drop = sorted(n for n, e in worst.items() if e > cfg.max_camera_cube_px)
    _deregister(rec, drop)
    if drop:
        log.warning("%d frame(s) left out: the cube reprojects far from their own markers (%s)", len(drop),
                    shown_names(drop))
        report["events"].append(f"{len(drop)} frame(s) whose markers the cube misses left out")
    report["cube_misses"] = drop


def calibrate_model(rec, markers: Markers, cube: CubeSpec, cfg: PosesConfig, sfm: bool, report: dict,
                    order: list[str] | None = None, refine_distortion: bool = True):
    """Move ``rec`` into the cube frame (cm, z up); with ``sfm``, bundle-adjust on the cube's corners (the lens
    distortion too with ``refine_distortion``). Returns the calibration (None without markers). ``order``: the frames
    in video order, for the scale's uncertainty."""
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
            n_ctrl = refine_with_cube(rec, det, cal, cube, MAP_THREADS, refine_distortion=refine_distortion,
                                      loss_scale_px=cfg.ba_loss_px)
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
    faces = face_offsets(pts, cube, cfg.face_band_cm, cfg.face_margin_cm, cfg.face_min_points)
    if faces:
        worst = max(faces, key=lambda f: abs(faces[f][0]))
        out.append(Check("cube_face_offset_cm", abs(faces[worst][0]), cfg.max_face_offset_cm, "<=",
                         f"SfM points on the cube's {worst} face (of {len(faces)} faces seen)"))
    return out


def model_checks(rec, cal, markers: Markers, cube: CubeSpec, names: list[str], times: list[float],
                 cfg: PosesConfig) -> list[Check]:
    """Every check of the final model (see :mod:`plantsplat.poses.checks`)."""
    reg = len(registered_images(rec))
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



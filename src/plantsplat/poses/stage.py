"""The poses stage over a workspace: what it reads, what it writes, and :func:`run`.

It reads the frames (``WS/images/``, ``WS/frames.json`` for their times in the video) and, when asked, a user's
COLMAP model or ``transforms.json``; it writes the model (``WS/sparse/0`` binary, ``WS/sparse_text/0`` text), its
points (``WS/sparse_points.ply``), nerfstudio's ``WS/transforms.json``, the cube's markers (``WS/markers.json``)
and the report ``WS/poses.json``. Registration, calibration and the checks are :mod:`plantsplat.poses.estimate`.

1. The cube's markers are detected once (:mod:`plantsplat.markers`, ``WS/markers.json``): with SfM and more than
   one thread in a process of their own at the lowest priority, beside step 2 (:func:`start_markers`).
2. The frames are registered by SfM (:func:`~plantsplat.poses.estimate.register`), or a model is imported.
3. The cube gives scale, gravity and origin (:func:`~plantsplat.poses.estimate.calibrate_model`); frames off the
   camera's path are left out, then those left out are localised against the model.
4. The model is checked (:func:`~plantsplat.poses.estimate.model_checks`). A model that fails a check is not
   written: the stage stops with a one-line error naming the check (exit code 3).

Usage:
    from plantsplat.poses import PosesConfig, stage
    report = stage.run(Workspace("ws/plant_01"), PosesConfig())
    report["registered"], report["total"], report["scale_source"]
"""

from __future__ import annotations

import json
import pickle
import subprocess
import time
from pathlib import Path

from plantsplat.checks import Check
from plantsplat.cube import CubeSpec
from plantsplat.errors import EXIT_POSES_FAILED, PlantsplatError, UsageError
from plantsplat.io import read_json, remove_tree, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.markers import Markers, detect_frames, log_found, write_markers
from plantsplat.poses.calibrate import up_vector
from plantsplat.poses.config import MIN_FRAMES, POSES_VERSION, WORK_DIR, PosesConfig
from plantsplat.poses.distortion import choose_distortion
from plantsplat.poses.estimate import (
    calibrate_model,
    import_model,
    leave_out_off_path,
    localize_left_out,
    model_checks,
    register,
    shown_names,
)
from plantsplat.poses.interop import registered_images, write_colmap, write_points_ply, write_transforms
from plantsplat.poses.marker_worker import error_file
from plantsplat.poses.sfm import MAP_THREADS, colmap_logging, n_threads_env
from plantsplat.pycolmap_loader import load_pycolmap
from plantsplat.workers import spawn_worker, stop_worker, worker_said
from plantsplat.workspace import Workspace

log = get_logger(__name__)

MARKERS_DIR = "markers"
"""The marker detection process's folder (:func:`start_markers`), in the stage's work folder."""
MARKERS_FILE = "markers.pickle"
"""What that process found, in its folder."""


def inputs(ws: Workspace, cfg: PosesConfig) -> list[Path]:
    """The files and folders the stage reads: the frames, their record and a model to import (if any)."""
    imports = [p for p in (cfg.import_colmap, cfg.import_transforms) if p is not None]
    return [ws.images_dir, ws.frames_json, *imports]


def outputs(ws: Workspace) -> list[Path]:
    """The files and folders the stage writes."""
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


def run(ws: Workspace | str | Path, cfg: PosesConfig | None = None) -> dict:
    """Run the poses stage on workspace ``ws``; returns the ``poses.json`` report.

    Usage:
        report = run(Workspace("ws/plant_01"), PosesConfig())
        report["registered"], report["total"], report["scale_source"]

    Raises :class:`PlantsplatError` on bad input (too few frames, broken import) and, with exit code 3,
    when the model fails its checks. Whether the stage needs to run at all is decided by
    :func:`plantsplat.pipeline.poses_stage`.
    """
    cfg = cfg or PosesConfig()
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    load_pycolmap()  # the poses modules' import of pycolmap replaced the CLI's SIGTERM handler: it is put back
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
    sfm = cfg.import_colmap is None and cfg.import_transforms is None
    beside = start_markers(ws, names, cube) if sfm and cfg.calibrate and cfg.num_threads > 1 else None
    markers = None if beside else detect_markers(ws, names, cube, cfg, report)
    times = video_times(ws, names)
    try:
        rec = register(ws, names, times, cfg, report) if sfm else import_model(ws, names, cfg, report)
        t0 = time.perf_counter()
        distortion = True
        if sfm and cfg.distortion == "auto":
            with colmap_logging(cfg.colmap_log):
                rec, distortion = choose_distortion(rec, MAP_THREADS, cfg.ba_loss_px, report)
        report["timings"]["distortion_s"] = time.perf_counter() - t0
        if beside:
            markers = finish_markers(ws, beside, cube, report)
    finally:
        stop_worker(beside)  # Ctrl-C or an error: the detection does not go on
    t0 = time.perf_counter()
    cal = calibrate_model(rec, markers, cube, cfg, sfm, report, [n for _, n in sorted(zip(times, names))], distortion)
    report["timings"]["calibrate_s"] = time.perf_counter() - t0
    if sfm and cal is not None:  # the cube's bundle adjustment moves weakly held cameras: judge the path again
        leave_out_off_path(rec, names, times, cfg, report)
    if sfm:
        localize_left_out(rec, ws, names, times, cfg, report)
    if cal is None and cfg.calibrate:
        log.warning("%s", unscaled_message(markers, {im.name for im in rec.images.values()}, ws.images_dir, cube))
        report["events"].append("no markers: unscaled model" if not any(markers.frames.values()) else
                                "markers too few or inconsistent: unscaled model")
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
    write_outputs(ws, rec, cal, report, cfg)
    write_json_atomic(ws.poses_json, report)
    log.info("poses: %d/%d frames registered, reprojection %s px, scale %s", report["registered"], len(names),
             "n/a" if report["mean_reprojection_error_px"] is None else f"{report['mean_reprojection_error_px']:.2f}",
             f"from the cube ({cal.median_residual_px:.2f} px marker residual)" if cal else "NONE (model units)")
    if report["unregistered"]:
        log.warning("%d frame(s) are left out: %s", len(report["unregistered"]), shown_names(report["unregistered"]))
    return report


def _describe(report: dict, rec, cal, cfg: PosesConfig, names: list[str]) -> None:
    """The report's calibration, registration and camera entries."""
    if cal is not None:
        report.update(scale_source="aruco", similarity=cal.summary(), up_vector_model=up_vector(cal),
                      marker_residuals_px=cal.frame_residuals_px, units="cm",
                      cube={"size_cm": cfg.cube_size, "marker_size_cm": cfg.marker_size, "dictionary": cfg.dictionary},
                      world="cube frame: origin at the centre of the cube's bottom face (ground plane), +z up, centimetres")
    else:
        report.update(scale_source="none", units="model units", world="COLMAP model frame (arbitrary scale and orientation)")
    reg = registered_images(rec)
    report["registered"] = len(reg)
    report["unregistered"] = [n for n in names if n not in reg]
    report["mean_reprojection_error_px"] = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None
    report["num_points"] = int(rec.num_points3D())
    cam = rec.cameras[next(iter(rec.cameras))]
    report["camera"] = {"model": cam.model.name, "params": list(map(float, cam.params)), "width": cam.width,
                        "height": cam.height}


def write_outputs(ws: Workspace, rec, cal, report: dict, cfg: PosesConfig) -> None:
    """The model as COLMAP binary and text, its points as a PLY and its cameras as nerfstudio's ``transforms.json``."""
    with colmap_logging(cfg.colmap_log):
        write_colmap(rec, ws.sparse_dir)
        write_colmap(rec, ws.sparse_text_dir, text=True)
    write_points_ply(rec, ws.sparse_points_ply)
    extra = {"ply_file_path": ws.sparse_points_ply.name,
             "plantsplat": {"units": report["units"], "world": report["world"], "scale_source": report["scale_source"]}}
    if cal is not None:
        extra["plantsplat"]["cube_from_model"] = cal.matrix().tolist()
    write_transforms(rec, ws.transforms_json, mask_prefix=ws.masks_dir.name, extra=extra)


def detect_markers(ws: Workspace, names: list[str], cube: CubeSpec, cfg: PosesConfig, report: dict) -> Markers:
    """The cube's markers in every frame (none without ``cfg.calibrate``), written to ``WS/markers.json``."""
    t0 = time.perf_counter()
    markers = detect_frames(ws.images_dir, names, cube) if cfg.calibrate else Markers(names=list(names))
    _record_markers(ws, markers, cube, report, time.perf_counter() - t0)
    return markers


def start_markers(ws: Workspace, names: list[str], cube: CubeSpec) -> subprocess.Popen:
    """:func:`detect_markers` in a process of its own at the lowest priority (:mod:`plantsplat.poses.marker_worker`),
    beside structure from motion, which leaves one core idle in its one-thread steps; :func:`finish_markers` collects
    them. Its folder is fresh."""
    here = (ws.root / WORK_DIR / MARKERS_DIR).resolve()
    remove_tree(here)
    here.mkdir(parents=True)
    (here / "names.txt").write_text("".join(f"{n}\n" for n in names))
    return spawn_worker("plantsplat.poses.marker_worker", [str(ws.images_dir.resolve()), str(here / "names.txt"),
                                                            json.dumps(cube.record()), str(here / MARKERS_FILE)], here)


def unscaled_message(markers: Markers, registered: set[str], images_dir: Path, cube: CubeSpec) -> str:
    """What the stage says when the cube gave the model no scale: no marker found at all, or markers found in too
    few registered frames (the cube needs two or more), or found but not fitting one cube."""
    seen = sorted(n for n, d in markers.frames.items() if d)
    after = ("the model is NOT metric and z is not up; traits will be in model units unless the traits stage finds "
             "the cube in the point cloud")
    if not seen:
        return f"NO CUBE MARKERS FOUND in {images_dir} (dictionary {cube.dictionary}): {after}"
    held = [n for n in seen if n in registered]
    if len(held) < 2:
        return (f"THE CUBE GAVE NO SCALE: its markers were found in {len(seen)} frame(s), {len(held)} of them "
                f"registered; it needs them in two registered frames or more (film it from several sides): {after}")
    return (f"THE CUBE GAVE NO SCALE: its markers, found in {len(held)} registered frames, do not fit one "
            f"{cube.size:g} cm cube (check --poses.cube-size and --poses.marker-size): {after}")


def finish_markers(ws: Workspace, proc: subprocess.Popen, cube: CubeSpec, report: dict) -> Markers:
    """The markers of the process :func:`start_markers` started, once it ends, written to ``WS/markers.json``; its
    error as one line when it fails."""
    here = ws.root / WORK_DIR / MARKERS_DIR
    code = proc.wait()
    if error_file(here / MARKERS_FILE).is_file():  # a frame's own one-line error
        error = read_json(error_file(here / MARKERS_FILE))
        raise PlantsplatError(error["message"], exit_code=error["exit_code"])
    if code != 0:
        raise PlantsplatError(f"{here}: the marker detection process ended with code {code} ({worker_said(here)}); "
                              "re-run with --poses.num-threads 1 to detect them in this process")
    with open(here / MARKERS_FILE, "rb") as f:
        found = pickle.load(f)
    remove_tree(here)
    _record_markers(ws, found["markers"], cube, report, found["seconds"])
    log_found(found["markers"])
    return found["markers"]


def _record_markers(ws: Workspace, markers: Markers, cube: CubeSpec, report: dict, seconds: float) -> None:
    write_markers(ws.markers_json, markers, cube)
    report["timings"]["detect_markers_s"] = seconds
    report["frames_with_markers"] = len(markers.frames)
    report["marker_edge_shift_px"] = markers.edge_shift_px


def _fail(ws: Workspace, rec, report: dict, failed: list[Check], cfg: PosesConfig) -> PlantsplatError:
    """Record a model that failed its checks (kept aside for inspection, not written as the output)."""
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

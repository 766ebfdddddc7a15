"""The stages and the end-to-end runner: frames -> poses -> segment -> train -> export -> traits (-> evaluate, report).

Each stage is a plain function over the workspace; the ``*_stage`` functions here run it through
:func:`plantsplat.stages.run_stage`, alike for ``plantsplat run``, ``batch`` and the stage's own
command: it runs only when its record does not say ``ok`` for today's options, inputs and outputs,
and never on top of an upstream stage that failed or was interrupted. Each stage takes its own
config dataclass (the one source of its options and defaults); :class:`RunConfig` composes them, so
every stage option is reachable from ``plantsplat run`` (``--poses.matcher``, ``--train.iterations``...).
Per-stage time and peak memory, versions and the full configuration go to ``WS/run.json``.

Usage:
    summary = run_pipeline("video.mp4", "ws/plant_01", RunConfig())
    summary["traits"]["quality"]
"""

from __future__ import annotations

import dataclasses
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from plantsplat import __version__
from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.export.config import ExportConfig
from plantsplat.frames.config import FramesConfig
from plantsplat.groundtruth import compare_traits, load_ground_truth
from plantsplat.io import read_json, write_json_atomic
from plantsplat.kernel_cache import kernels_cached
from plantsplat.lock import workspace_lock
from plantsplat.log import get_logger
from plantsplat.options import check_options
from plantsplat.poses.config import PosesConfig
from plantsplat.preflight import check_masks_are_ours, check_run
from plantsplat.resources import StageMeter, machine_info
from plantsplat.segment.config import SegmentConfig
from plantsplat.stages import read_record, require_ok, run_stage
from plantsplat.train.config import TrainConfig
from plantsplat.traits.config import TraitsConfig
from plantsplat.workers import spawn_worker
from plantsplat.workspace import Workspace

log = get_logger(__name__)

WARMUP_MODULE = "plantsplat.train.warmup"
_warmup: list[subprocess.Popen] = []  # this process's kernel warm-up (start_kernel_warmup)


@dataclass
class RunConfig:
    """Every stage's options, for `plantsplat run`, `demo` and `batch` (each stage's defaults otherwise)."""

    frames: FramesConfig = field(default_factory=FramesConfig)
    poses: PosesConfig = field(default_factory=PosesConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    traits: TraitsConfig = field(default_factory=TraitsConfig)
    report: bool = True
    """Write `report.html` at the end."""
    # set by the `run`, `demo` and `batch` commands, not options of their own:
    ground_truth: tyro.conf.Suppress[Path | None] = None
    """Ground truth (a synth or rendered capture's ground_truth.json, or a CSV of measured traits) to evaluate against."""
    plant_id: tyro.conf.Suppress[str | None] = None
    """Plant id that picks the row of a ground-truth CSV (default: the workspace folder name)."""


# --- the stages ---------------------------------------------------------------------------------


def frames_stage(ws: Workspace, source: Path, cfg: FramesConfig, force: bool = False) -> dict:
    """Frames from a video or image folder (:func:`plantsplat.frames.stage.run`)."""
    from plantsplat.frames import stage as frame_extraction  # deferred: PyAV is slow to load (the CLI imports this module)

    check_options(cfg, "frames")
    frame_extraction.check_not_inside(source, ws)
    if ws.image_names() and read_record(ws, "frames") is None and not force:
        raise UsageError(f"{ws.images_dir}: holds images this workspace's frames stage did not write; pass --force to "
                         "replace them, or choose another workspace (your images are left as they are)")
    return run_stage(ws, "frames", {"source": str(Path(source).resolve()), **dataclasses.asdict(cfg)},
                     frame_extraction.inputs(ws, source), frame_extraction.outputs(ws),
                     lambda resume: frame_extraction.run(ws, cfg, source), force)


def poses_stage(ws: Workspace, cfg: PosesConfig, force: bool = False) -> dict:
    """Camera poses calibrated with the cube (:func:`plantsplat.poses.stage.run`)."""
    from plantsplat.poses import stage as pose_estimation  # deferred: scipy's rotations are slow to load (CLI start-up)

    check_options(cfg, "poses")
    require_ok(ws, "frames")
    return run_stage(ws, "poses", _without(cfg, "colmap_log", "num_threads"), pose_estimation.inputs(ws, cfg),
                     pose_estimation.outputs(ws), lambda resume: pose_estimation.run(ws, cfg), force)


def segment_stage(ws: Workspace, cfg: SegmentConfig, force: bool = False) -> dict:
    """Masks of the plant and the cube (:func:`plantsplat.segment.stage.run`); an interrupted run with the same
    options and inputs resumes from the checkpoint of its quick scene model."""
    from plantsplat.segment import stage as segmentation  # deferred: it loads torch and OpenCV

    check_options(cfg, "segment")
    check_masks_are_ours(ws)
    require_ok(ws, "poses")
    return run_stage(ws, "segment", _without(cfg, "preview", "device"), segmentation.inputs(ws, cfg),
                     segmentation.outputs(ws), lambda resume: segmentation.run(ws, cfg, resume), force)


def train_stage(ws: Workspace, cfg: TrainConfig, force: bool = False) -> dict:
    """The object-centric (or full-scene) Gaussian model (:func:`plantsplat.train.stage.run`); an
    interrupted run with the same options and inputs resumes from its checkpoint."""
    from plantsplat.train import stage as training  # deferred: it loads torch

    check_options(cfg, "train")
    require_ok(ws, "poses")
    require_ok(ws, "segment")
    return run_stage(ws, "train", _without(cfg, "threads", "checkpoint_seconds"), training.inputs(ws, cfg),
                     training.outputs(ws, cfg), lambda resume: training.run(ws, cfg, resume=resume), force)


def export_stage(ws: Workspace, cfg: ExportConfig, force: bool = False) -> dict:
    """The 3DGS PLY and the point cloud (:func:`plantsplat.export.stage.run`)."""
    from plantsplat.export import stage as model_export  # deferred: it loads torch

    check_options(cfg, "export")
    require_ok(ws, "train")
    return run_stage(ws, "export", cfg, model_export.inputs(ws, cfg), model_export.outputs(ws),
                     lambda resume: model_export.run(ws, cfg), force)


def traits_stage(ws: Workspace, cfg: TraitsConfig, force: bool = False, points: Path | None = None,
                 calibrated: bool | None = None, figure: bool = True) -> dict:
    """Traits and the checks that decide their quality (:func:`plantsplat.traits.stage.run`);
    ``points``: measure this PLY instead of the workspace's export."""
    from plantsplat.traits import stage  # deferred: it loads SciPy, Open3D, torch and matplotlib

    check_options(cfg, "traits")
    if points is None:
        require_ok(ws, "export")
    config = {**dataclasses.asdict(cfg), "points": str(Path(points).resolve()) if points else None,
              "calibrated": calibrated, "figure": figure}
    return run_stage(ws, "traits", config, stage.inputs(ws, points), stage.outputs(ws),
                     lambda resume: stage.run(ws, cfg, points_path=points, calibrated=calibrated, figure=figure),
                     force)


def evaluate_stage(ws: Workspace, ground_truth: Path, plant_id: str | None, force: bool = False) -> dict:
    """The traits against ground truth (:func:`evaluate_traits`)."""
    require_ok(ws, "traits")
    return run_stage(ws, "evaluate", {"ground_truth": str(Path(ground_truth).resolve()), "plant_id": plant_id},
                     [ws.traits_json, Path(ground_truth)], [evaluation_json(ws)],
                     lambda resume: evaluate_traits(ws, ground_truth, plant_id), force)


def report_stage(ws: Workspace) -> dict:
    """``report.html`` (always written again: it shows every stage as it is now)."""
    from plantsplat.report.plant import write_report  # deferred: it loads OpenCV and matplotlib

    return {"report": str(write_report(ws))}


def _without(cfg, *fields: str) -> dict:
    """A stage config as a dict, less the fields that do not change its result (logging, threads, devices)."""
    return {k: v for k, v in dataclasses.asdict(cfg).items() if k not in fields}


# --- evaluation ---------------------------------------------------------------------------------


def evaluation_json(ws: Workspace) -> Path:
    return ws.root / "evaluation.json"


def evaluate_traits(ws: Workspace, ground_truth: Path | None, plant_id: str | None = None) -> dict:
    """Compare ``WS/traits.json`` with ground truth; writes ``WS/evaluation.json``."""
    if ground_truth is None or not str(ground_truth).strip():
        raise UsageError("evaluate needs --ground-truth (a synth ground_truth.json or a CSV of measured traits)")
    traits = read_json(ws.require(ws.traits_json, "traits"))
    truth = load_ground_truth(ground_truth, plant_id)  # raises before anything is written
    comparison = compare_traits(traits, truth)
    result = {"ground_truth": str(ground_truth), "plant_id": plant_id, "quality": traits.get("quality"),
              "traits": comparison}
    write_json_atomic(evaluation_json(ws), result)
    return result


# --- the runner ---------------------------------------------------------------------------------


def _plan(source: Path | None, cfg: RunConfig) -> list[tuple[str, object]]:
    """The stages `plantsplat run` runs for ``cfg``, in order, each with a function of (workspace, force)."""
    plan = [
        ("frames", lambda ws, f: frames_stage(ws, source, cfg.frames, f)),
        ("poses", lambda ws, f: poses_stage(ws, cfg.poses, f)),
        ("segment", lambda ws, f: segment_stage(ws, cfg.segment, f)),
        ("train", lambda ws, f: train_stage(ws, cfg.train, f)),
        ("export", lambda ws, f: export_stage(ws, cfg.export, f)),
        ("traits", lambda ws, f: traits_stage(ws, cfg.traits, f)),
    ]
    if cfg.ground_truth is not None:
        plan.append(("evaluate", lambda ws, f: evaluate_stage(ws, cfg.ground_truth, cfg.plant_id or ws.root.name, f)))
    if cfg.report:
        plan.append(("report", lambda ws, f: report_stage(ws)))
    return plan


def run_pipeline(source: str | Path | None, ws_root: str | Path, cfg: RunConfig, force: bool = False) -> dict:
    """Run (or resume) the whole pipeline for one plant; returns the summary (traits, metrics, paths).

    ``source``: the video or image folder (None: the workspace already holds its frames). A stage that
    fails stops the run with its error; what the stages before it wrote is kept.
    """
    check_run(source, ws_root, cfg)  # inputs, option values and the workspace, before any stage runs
    start_kernel_warmup()
    ws = Workspace(ws_root)
    ws.root.mkdir(parents=True, exist_ok=True)
    with workspace_lock(ws.root):  # one process at a time on a workspace
        _run_stages(ws, Path(source) if source is not None else None, cfg, force)
    return summarize_workspace(ws)


def start_kernel_warmup() -> subprocess.Popen | None:
    """Start the kernel warm-up process (:mod:`plantsplat.train.warmup`: it compiles the CPU kernels beside the first
    stages) once per process, where numba's cache is not known to hold them (:mod:`plantsplat.kernel_cache`); return
    it, or None where the kernels are cached. Nothing waits for it."""
    if not _warmup:
        if kernels_cached():
            return None
        _warmup.append(spawn_worker(WARMUP_MODULE, [], None))
    _warmup[0].poll()  # reaps it once it has ended
    return _warmup[0]


def _run_stages(ws: Workspace, src: Path | None, cfg: RunConfig, force: bool) -> None:
    record: dict = {"machine": machine_info(), "stages": {}}
    for name, fn in _plan(src, cfg):
        if name == "frames" and src is None:
            require_ok(ws, "frames", f"plantsplat frames VIDEO --out {ws.root}")
            continue
        with StageMeter() as meter:
            try:
                result = fn(ws, force)
            except PlantsplatError as exc:
                record["stages"][name] = {"failed": str(exc)}
                record["failed_stage"] = name
                try:
                    _write_run_json(ws, record, cfg, src)
                except PlantsplatError as also:  # a full disk: the stage's error names the write that failed
                    log.warning("could not update %s: %s", ws.run_json, also)
                raise
        record["stages"][name] = {"seconds": round(meter.seconds, 2), "cpu_seconds": round(meter.cpu_seconds, 2),
                                  "peak_rss_mb": round(meter.peak_rss_mb, 1), "result": _scalars(result)}
        _write_run_json(ws, record, cfg, src)


def _scalars(result) -> dict:
    return {k: v for k, v in (result or {}).items() if isinstance(v, (int, float, str, bool)) or v is None}


def _write_run_json(ws: Workspace, record: dict, cfg: RunConfig, source: Path | None) -> None:
    prev = {}
    if ws.run_json.is_file():
        try:
            prev = read_json(ws.run_json)
        except PlantsplatError:
            prev = {}
    stages = dict(prev.get("stages", {}))
    for name, entry in record.get("stages", {}).items():
        if not (entry.get("result", {}).get("up_to_date") and name in stages):  # keep the run that did the work
            stages[name] = entry
    data = {
        "plantsplat_version": __version__,
        "source": str(source) if source else prev.get("source"),
        "config": dataclasses.asdict(cfg),
        "machine": record.get("machine") or machine_info(),
        "stages": stages,
        "total_seconds": round(sum(s.get("seconds", 0.0) for s in stages.values() if isinstance(s, dict)), 2),
        "failed_stage": record.get("failed_stage"),
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_json_atomic(ws.run_json, data)


def summarize_workspace(ws: Workspace) -> dict:
    """Traits, image metrics, evaluation and output paths of a finished workspace."""
    out: dict = {"workspace": str(ws.root)}
    for key, path in [("traits", ws.traits_json), ("metrics", ws.metrics_json), ("evaluation", evaluation_json(ws)),
                      ("run", ws.run_json)]:
        if path.is_file():
            out[key] = read_json(path)
    out["outputs"] = {
        name: str(p)
        for name, p in [("splat", ws.splat_ply), ("points", ws.points_ply), ("plant", ws.plant_ply),
                        ("traits", ws.traits_json), ("traits_csv", ws.traits_csv), ("traits_figure", ws.traits_png),
                        ("transforms", ws.transforms_json), ("colmap", ws.sparse_dir), ("report", ws.report_html)]
        if p.exists()
    }
    return out

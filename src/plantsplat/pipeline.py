"""The end-to-end runner: frames -> poses -> segment -> train -> export -> traits (-> evaluate, report).

Each stage is a plain function over the workspace (see :mod:`plantsplat.workspace`). The runner
records a stamp per finished stage (its configuration fingerprint and finish time) in
``WS/.plantsplat/stamps/``; a stage is skipped when its stamp matches the current configuration,
its outputs exist and no upstream stage finished after it, so an interrupted run resumes where it
stopped and a changed option re-runs only the stages it affects. Per-stage time and peak memory,
versions and the full configuration go to ``WS/run.json``.

Example:
    >>> from plantsplat.pipeline import RunOptions, run_pipeline
    >>> summary = run_pipeline("video.mp4", "ws/plant_01", RunOptions())  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from plantsplat import __version__
from plantsplat.errors import PlantsplatError
from plantsplat.io import read_json, write_json_atomic
from plantsplat.log import get_logger
from plantsplat.resources import StageMeter, machine_info
from plantsplat.workspace import Workspace

log = get_logger(__name__)


@dataclass
class RunOptions:
    """Options of `plantsplat run` (each stage's defaults otherwise)."""

    num_frames: int = 120
    """Frames to keep from the video (the paper: 100-150)."""
    max_size: int = 960
    """Longest side of the working images, in pixels (the paper trains at 1/4 of 4K)."""
    segment_backend: Literal["3d", "sam2"] = "3d"
    """Segmenter: `3d` (the plant decided in 3D, offline, no weights) or `sam2` (needs --sam2-checkpoint)."""
    sam2_checkpoint: Path | None = None
    """SAM-2 checkpoint file for `--segment-backend sam2`."""
    import_masks: Path | None = None
    """Use your own masks from this folder instead of segmenting (one per frame, named like the frames)."""
    matcher: Literal["auto", "retrieval", "exhaustive"] = "auto"
    """COLMAP feature matching (`auto`: every pair for short captures, else video neighbours and retrieval)."""
    import_colmap: Path | None = None
    """Use your own COLMAP model (folder, .bin or .txt) instead of running SfM (still calibrated with the cube)."""
    import_transforms: Path | None = None
    """Use your own nerfstudio transforms.json instead of running SfM (still calibrated with the cube)."""
    mode: Literal["object", "full"] = "object"
    """Training mode: `object` (RGBA, the paper's method) or `full` (whole scene, the Splatfacto baseline)."""
    backend: Literal["auto", "cpu", "gsplat"] = "auto"
    """Rasterizer: `auto` uses gsplat on a CUDA GPU, else the CPU backend."""
    iterations: int | None = None
    """Training iterations (default: the trainer's recipe for the chosen backend)."""
    report: bool = True
    """Write `report.html` at the end (when the report stage is installed)."""
    seed: int = 0
    """Random seed for training."""
    # set by the `run`, `demo` and `batch` commands, not options of their own:
    ground_truth: tyro.conf.Suppress[Path | None] = None
    """Ground truth (a synth `ground_truth.json` or a CSV of measured traits) to evaluate against."""
    plant_id: tyro.conf.Suppress[str | None] = None
    """Plant id that picks the row of a ground-truth CSV (default: the workspace folder name)."""


@dataclass
class Stage:
    name: str
    run: Callable[[Workspace, Path | None, RunOptions], dict]
    outputs: Callable[[Workspace], list[Path]]
    options: tuple[str, ...] = ()
    """RunOptions fields that change this stage's result (part of its fingerprint)."""
    optional: bool = False


STAMP_DIR = ".plantsplat/stamps"


def _fingerprint(stage: Stage, opts: RunOptions, source: Path | None) -> str:
    data = {k: str(getattr(opts, k)) for k in stage.options}
    if stage.name == "frames":
        data["source"] = str(source.resolve()) if source else None
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def _stamp_path(ws: Workspace, name: str) -> Path:
    return ws.root / STAMP_DIR / f"{name}.json"


def _read_stamp(ws: Workspace, name: str) -> dict | None:
    p = _stamp_path(ws, name)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def stage_up_to_date(ws: Workspace, stage: Stage, upstream: list[Stage], opts: RunOptions, source: Path | None) -> bool:
    stamp = _read_stamp(ws, stage.name)
    if not stamp or stamp.get("fingerprint") != _fingerprint(stage, opts, source):
        return False
    if not all(p.exists() for p in stage.outputs(ws)):
        return False
    for up in upstream:
        ups = _read_stamp(ws, up.name)
        if ups is not None and ups.get("finished", 0) > stamp.get("finished", 0):
            return False
    return True


def _summarise(result: dict | None) -> dict:
    """Keep the JSON-friendly scalars of a stage's result for run.json."""
    out = {}
    for k, v in (result or {}).items():
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[k] = v
    return out


def run_stages(
    ws: Workspace,
    stages: list[Stage],
    opts: RunOptions,
    source: Path | None = None,
    record: dict | None = None,
) -> dict:
    """Run ``stages`` in order, skipping the ones that are up to date; returns the run record."""
    record = record if record is not None else {}
    record.setdefault("stages", {})
    done: list[Stage] = []
    for stage in stages:
        if stage_up_to_date(ws, stage, done, opts, source):
            log.info("[%s] up to date, skipped", stage.name)
            record["stages"].setdefault(stage.name, {})["skipped"] = True
            done.append(stage)
            continue
        log.info("[%s] running", stage.name)
        with StageMeter() as meter:
            try:
                result = stage.run(ws, source, opts)
            except PlantsplatError as exc:
                record["stages"][stage.name] = {"failed": str(exc)}
                record["failed_stage"] = stage.name
                _write_run_json(ws, record, opts, source)
                raise
        entry = {"seconds": round(meter.seconds, 2), "peak_rss_mb": round(meter.peak_rss_mb, 1), "skipped": False}
        entry.update({"result": _summarise(result)})
        record["stages"][stage.name] = entry
        write_json_atomic(
            _stamp_path(ws, stage.name),
            {"fingerprint": _fingerprint(stage, opts, source), "finished": time.time()},
        )
        _write_run_json(ws, record, opts, source)
        log.info("[%s] done in %.1f s (peak %.0f MB)", stage.name, meter.seconds, meter.peak_rss_mb)
        done.append(stage)
    record.pop("failed_stage", None)
    return record


def _write_run_json(ws: Workspace, record: dict, opts: RunOptions, source: Path | None) -> None:
    prev = {}
    if ws.run_json.is_file():
        try:
            prev = read_json(ws.run_json)
        except PlantsplatError:
            prev = {}
    stages = dict(prev.get("stages", {}))
    for name, entry in record.get("stages", {}).items():
        if entry.get("skipped") and name in stages:
            continue  # keep the timing of the run that actually did the work
        stages[name] = entry
    data = {
        "plantsplat_version": __version__,
        "source": str(source) if source else prev.get("source"),
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(opts).items()},
        "machine": record.get("machine") or machine_info(),
        "stages": stages,
        "total_seconds": round(sum(s.get("seconds", 0.0) for s in stages.values() if isinstance(s, dict)), 2),
        "failed_stage": record.get("failed_stage"),
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_json_atomic(ws.run_json, data)


# --- the stages of `plantsplat run` ------------------------------------------------------------


def _stage_frames(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.frames import extract_frames

    if source is None:
        raise PlantsplatError(f"{ws.root}: no input video or image folder given")
    # a finished extraction with other settings (its stamp differs) is redone; without a stamp the
    # stage resumes, and refuses to replace frames it did not extract itself
    redo = _read_stamp(ws, "frames") is not None
    return extract_frames(source, ws, num=opts.num_frames, max_size=opts.max_size, force=redo)


def _stage_segment(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.segment import segment_workspace
    from plantsplat.segment.config import SegmentConfig

    return segment_workspace(ws, SegmentConfig(backend=opts.segment_backend, sam2_checkpoint=opts.sam2_checkpoint,
                                               import_masks=opts.import_masks, seed=opts.seed))


def _stage_poses(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.poses import PosesConfig, estimate_poses

    return estimate_poses(
        ws,
        PosesConfig(matcher=opts.matcher, import_colmap=opts.import_colmap, import_transforms=opts.import_transforms),
    )


def _stage_train(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.train import TrainConfig, train_workspace

    return train_workspace(ws, TrainConfig(mode=opts.mode, backend=opts.backend, seed=opts.seed, iterations=opts.iterations))


def _stage_export(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.train import export_workspace

    return export_workspace(ws)


def _stage_traits(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.traits import traits_workspace

    return traits_workspace(ws)


def _stage_evaluate(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    return evaluate_workspace(ws, opts.ground_truth, opts.plant_id or ws.root.name)


def _stage_report(ws: Workspace, source: Path | None, opts: RunOptions) -> dict:
    from plantsplat.report import write_report

    path = write_report(ws)
    return {"report": str(path)}


def evaluation_json(ws: Workspace) -> Path:
    return ws.root / "evaluation.json"


def evaluate_workspace(ws: Workspace, ground_truth: Path | None, plant_id: str | None = None) -> dict:
    """Compare ``WS/traits.json`` with ground truth; writes ``WS/evaluation.json``."""
    from plantsplat.groundtruth import compare_traits, load_ground_truth

    if ground_truth is None:
        raise PlantsplatError("evaluate needs --ground-truth (a synth ground_truth.json or a CSV of measured traits)")
    traits = read_json(ws.require(ws.traits_json, "traits"))
    truth = load_ground_truth(ground_truth, plant_id)
    comparison = compare_traits(traits, truth)
    result = {"ground_truth": str(ground_truth), "plant_id": plant_id, "traits": comparison}
    write_json_atomic(evaluation_json(ws), result)
    return result


def pipeline_stages(opts: RunOptions) -> list[Stage]:
    """The stages `plantsplat run` executes for these options, in order."""
    stages = [
        Stage("frames", _stage_frames, lambda w: [w.frames_json, w.images_dir], ("num_frames", "max_size")),
        Stage("poses", _stage_poses, lambda w: [w.sparse_dir, w.transforms_json, w.poses_json, w.markers_json], ("matcher", "import_colmap", "import_transforms")),
        Stage("segment", _stage_segment, lambda w: [w.masks_dir, w.segment_json], ("segment_backend", "sam2_checkpoint", "import_masks", "seed")),
        Stage("train", _stage_train, lambda w: [w.train_dir, w.metrics_json], ("mode", "backend", "iterations", "seed")),
        Stage("export", _stage_export, lambda w: [w.splat_ply, w.points_ply]),
        Stage("traits", _stage_traits, lambda w: [w.traits_json, w.traits_csv]),
    ]
    if opts.ground_truth is not None:
        stages.append(Stage("evaluate", _stage_evaluate, lambda w: [evaluation_json(w)], ("ground_truth", "plant_id")))
    if opts.report:
        try:
            import plantsplat.report  # noqa: F401
        except ImportError:
            pass
        else:
            stages.append(Stage("report", _stage_report, lambda w: [w.report_html], optional=True))
    return stages


def run_pipeline(source: str | Path | None, ws_root: str | Path, opts: RunOptions) -> dict:
    """Run (or resume) the whole pipeline for one plant; returns the summary (traits, metrics, paths)."""
    ws = Workspace(ws_root)
    ws.root.mkdir(parents=True, exist_ok=True)
    src = Path(source) if source is not None else None
    if src is not None and not src.exists():
        raise PlantsplatError(f"{src}: input not found (a video file or a folder of images)")
    record: dict = {"machine": machine_info()}
    stages = pipeline_stages(opts)
    run_stages(ws, stages, opts, src, record)
    return summarize_workspace(ws)


def summarize_workspace(ws: Workspace) -> dict:
    """Traits, image metrics, evaluation and output paths of a finished workspace."""
    out: dict = {"workspace": str(ws.root)}
    for key, path in [("traits", ws.traits_json), ("metrics", ws.metrics_json), ("evaluation", evaluation_json(ws)),
                      ("run", ws.run_json)]:
        if path.is_file():
            out[key] = read_json(path)
    out["outputs"] = {
        name: str(p)
        for name, p in [("splat", ws.splat_ply), ("points", ws.points_ply), ("traits", ws.traits_json),
                        ("traits_csv", ws.traits_csv), ("traits_figure", ws.traits_png), ("transforms", ws.transforms_json),
                        ("colmap", ws.sparse_dir), ("report", ws.report_html)]
        if p.exists()
    }
    return out

"""The segment stage over a workspace: what it reads, what it writes, and :func:`run`.

Runs after the poses stage: every registered frame has a calibrated camera. Backends:

- ``3d`` (default, offline, no weights): the object is decided in 3D (:mod:`plantsplat.segment.object3d`)
  in a quick whole-scene model (:mod:`plantsplat.segment.scene`), drawn into each frame and refined on
  the frame's own edges (:mod:`plantsplat.segment.frame`);
- ``sam2``: SAM-2's video predictor, prompted from the ``3d`` masks (:mod:`plantsplat.segment.sam2_backend`);
- your own masks: ``import_masks`` (:mod:`plantsplat.segment.imports`).

It reads the frames and the poses stage's model, cameras and markers (or the folder of ``import_masks``); it
writes (see :class:`plantsplat.workspace.Workspace`) ``masks/frame_*.png`` (uint8, 255 = plant or cube),
``rgba/frame_*.png`` (alpha = mask), ``segment.json`` (backend, settings, per frame the foreground share and
how sure the segmenter is, frames left out with the reason), ``masks_preview.png`` (a contact sheet that
shows the least sure frames first) and, for the ``3d`` backend, ``segment_decision.png`` (the quick model's
Gaussians by what they were decided to be: :mod:`plantsplat.segment.decision_figure`).

Usage:
    from plantsplat.segment import SegmentConfig, stage
    info = stage.run(Workspace("ws/plant01"), SegmentConfig())
    info["backend"], info["confidence"]["min"]
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.io import (
    atomic_path,
    png_params,
    read_image,
    read_json,
    staged_dir,
    write_image_atomic,
    write_json_atomic,
)
from plantsplat.log import get_logger, progress
from plantsplat.markers import recorded_cube
from plantsplat.resources import map_on_cores, usable_cores
from plantsplat.segment.config import SegmentConfig
from plantsplat.segment.decide import DecideConfig
from plantsplat.segment.decision_figure import decision_figure
from plantsplat.segment.frame import cached_distortion_map, object_mask, object_prior, to_frame, unresolved_px
from plantsplat.segment.imports import import_masks
from plantsplat.segment.object3d import object_model
from plantsplat.segment.preview import contact_sheet
from plantsplat.segment.sam2_backend import check_sam2, resolve_config, sam2_segment
from plantsplat.segment.scene import scene_model
from plantsplat.segment.scores import mask_iou
from plantsplat.segment.stored import save_object
from plantsplat.workspace import Workspace

log = get_logger(__name__)

SEGMENT_VERSION = 2
"""Version of ``segment.json``'s layout."""
FRACTION_DIGITS = 5
"""Decimals of the foreground shares in ``segment.json``."""
PREVIEW_LEAST_SURE = 4
"""The contact sheet shows the frames the segmenter is least sure of first, this many ..."""
PREVIEW_SPREAD = 12
"""... then this many frames spread evenly over the capture ..."""
PREVIEW_TILES = 16
"""... and at most this many frames in all."""


def _write_png(path: Path, img: np.ndarray) -> None:
    """Write a gray or BGR(A) uint8 image as PNG atomically, with fast compression (:func:`plantsplat.io.png_params`)."""
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img, png_params()):
            raise PlantsplatError(f"{path}: could not write image; check the disk space and permissions")


def inputs(ws: Workspace, cfg: SegmentConfig) -> list[Path]:
    """The files and folders the stage reads: the frames, the poses stage's outputs and the masks to import (if any)."""
    imports = [cfg.import_masks] if cfg.import_masks is not None else []
    return [ws.images_dir, ws.poses_json, ws.sparse_dir, ws.transforms_json, ws.markers_json, *imports]


def outputs(ws: Workspace) -> list[Path]:
    """The files and folders the stage writes."""
    return [ws.masks_dir, ws.rgba_dir, ws.segment_json]


def calibrated_cube(ws: Workspace):
    """The calibration cube when the poses stage calibrated the model with it (else None)."""
    if not ws.poses_json.is_file() or read_json(ws.poses_json).get("scale_source") != "aruco":
        return None
    return recorded_cube(ws.markers_json) or CubeSpec()


def _masks_3d(ws: Workspace, names: list[str], cfg: SegmentConfig, resume: bool = False,
              out_dirs: tuple[Path, Path] | None = None):
    """The ``3d`` backend: ``({name: (plant, cube) bool masks}, per-frame facts, capture facts)``. ``out_dirs``:
    ``(masks, rgba)`` folders each frame's mask and RGBA image are written into as soon as it is refined (the frame
    decoded once); None: nothing is written."""
    t0 = time.perf_counter()
    params, views, points = scene_model(ws, cfg, resume)
    t_model = time.perf_counter() - t0
    obj = object_model(params, views, calibrated_cube(ws), points, min_in_view=cfg.min_in_view,
                       sfm_reach=cfg.sfm_reach, seed=cfg.seed, decide=DecideConfig(enabled=cfg.weigh_evidence))
    save_object(ws, obj)
    if cfg.preview:
        decision_figure(obj, ws.segment_decision_png)
    by_name = {v.name: v for v in views}
    lenses: dict = {}  # one distortion map per camera (an imported model may hold one camera per frame)
    parts: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    facts: dict[str, dict] = {}
    pending: deque = deque()  # (name, the cube's share, the prior's mask, the refined mask's future), in frame order
    workers = usable_cores()
    with ThreadPoolExecutor(max_workers=workers) as pool:  # GrabCut and PNG coding release the GIL
        try:
            for name in progress(names, "segment: masks from the 3D object"):
                view = by_name.get(name)
                if view is None:
                    facts[name] = {"confidence": None, "note": "no camera pose (not registered by the poses stage)"}
                    if out_dirs is not None:
                        pending.append((name, None, None, pool.submit(_frame_mask, ws, name, None, cfg, out_dirs)))
                    continue
                maps = cached_distortion_map(view, lenses)
                plant, cube = (to_frame(p, maps) for p in object_prior(obj, view))  # rendered here: numba's threads
                prior = np.maximum(plant, cube) > 0.5
                pending.append((name, cube > 0.5, prior, pool.submit(_frame_mask, ws, name, (plant, cube), cfg,
                                                                     out_dirs, view.raw)))
                view.raw = view.image = view.mask = None  # the task holds the frame until its mask is written
                while len(pending) > 2 * workers:  # a few frames in flight, not all of them in memory
                    _finish_mask(pending.popleft(), parts, facts)
            while pending:
                _finish_mask(pending.popleft(), parts, facts)
        except BaseException:  # an error or Ctrl-C: the frames waiting are not refined
            pool.shutdown(cancel_futures=True)
            raise
    info = {"object": obj.info, "calibrated": obj.cube is not None, "sfm_points": int(len(points)),
            **({"decision_figure": ws.segment_decision_png.name} if cfg.preview else {}),
            "timing": {"scene_model_s": round(t_model, 2)}}
    return parts, facts, info


def _frame_mask(ws: Workspace, name: str, prior: tuple[np.ndarray, np.ndarray] | None, cfg: SegmentConfig,
                out_dirs: tuple[Path, Path] | None, rgb: np.ndarray | None = None) -> np.ndarray | None:
    """Frame ``name``'s mask from its prior ``(plant, cube)``: the outline refined on the frame, the cube kept
    (:func:`plantsplat.segment.frame.object_mask`); None without a prior (a frame with no camera). With ``out_dirs``,
    the mask and the RGBA image are written there. ``rgb``: the frame as decoded (read here when not given)."""
    if rgb is None and (out_dirs is not None or cfg.refine_band_px > 0):
        rgb = read_image(ws.images_dir / name)
    mask = None
    if prior is not None:
        mask = object_mask(rgb, *prior, cfg.refine_band_px, unresolved_px(prior[0].shape, cfg.scene_resolution),
                           seed=cfg.seed)
    if out_dirs is not None:
        _write_frame(name, rgb, mask, *out_dirs)
    return mask


def _finish_mask(item: tuple, parts: dict, facts: dict) -> None:
    """A refined mask split into plant and cube, with the segmenter's confidence (how little refining moved it)."""
    name, cube, prior, future = item
    mask = future.result()
    if mask is None:  # a frame without a camera, written out as all background
        return
    parts[name] = (mask & ~cube, mask & cube)
    facts[name] = {"confidence": round(mask_iou(prior, mask), 4)}


def run(ws: Workspace | str | os.PathLike, cfg: SegmentConfig | None = None, resume: bool = False) -> dict[str, Any]:
    """Run the segment stage: every frame in ``ws/images`` cut into plant + cube; writes masks, RGBA,
    ``segment.json`` and a preview, and returns ``segment.json``'s content.

    Needs the poses stage's cameras (``3d`` and ``sam2``), or the masks of ``cfg.import_masks``. The
    ``masks/`` and ``rgba/`` folders are each replaced whole when they are complete. Raises
    :class:`PlantsplatError` on bad input and when more than ``cfg.max_excluded`` of the frames have no
    plant (nothing is written then). ``resume``: go on from the checkpoint of the quick model of an
    interrupted run with the same options and inputs. Whether the stage needs to run at all is decided by
    :func:`plantsplat.pipeline.segment_stage`.

    Usage:
        info = run(Workspace("ws/plant01"), SegmentConfig(import_masks=Path("my_masks")))
        info["backend"], info["excluded"]
    """
    cfg = cfg or SegmentConfig()
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    if cfg.backend not in ("3d", "sam2"):
        raise UsageError(f"unknown segmentation backend {cfg.backend!r}; use 3d or sam2")
    names = ws.image_names()
    if not names:
        raise PlantsplatError(f"{ws.images_dir}: no images; run `plantsplat frames VIDEO --out {ws.root}` first")
    if cfg.import_masks is None and not (ws.sparse_dir.is_dir() or ws.transforms_json.is_file()):
        raise PlantsplatError(f"{ws.root}: no camera poses; run `plantsplat poses {ws.root}` first (the segmenter "
                              "decides the plant in 3D), or pass --import-masks DIR")
    t0 = time.perf_counter()
    if cfg.import_masks is None and cfg.backend == "3d":  # masks and RGBA written as each frame is refined
        with staged_dir(ws.masks_dir) as masks_dir, staged_dir(ws.rgba_dir) as rgba_dir:
            parts, facts, info = _masks_3d(ws, names, cfg, resume, (masks_dir, rgba_dir))
            masks = {n: p | c for n, (p, c) in parts.items()}
            per_frame, excluded = _frame_rows(ws, names, masks, facts, info, cfg)  # raises: nothing is written
        return _finish(ws, names, masks, per_frame, excluded, info, "3d", cfg, time.perf_counter() - t0)
    if cfg.import_masks is not None:
        masks, facts, info = import_masks(Path(cfg.import_masks), ws, names), {}, {"source": str(cfg.import_masks)}
        backend = "import"
    else:
        parts, facts, info = _masks_3d(ws, names, cfg, resume)
        masks, info["sam2"] = _sam2(ws, names, parts, cfg)
        backend = "sam2"
    per_frame, excluded = _frame_rows(ws, names, masks, facts, info, cfg)
    # every core: decoding and encoding PNGs release the GIL; the pool ends before a failed write's folders go
    with staged_dir(ws.masks_dir) as masks_dir, staged_dir(ws.rgba_dir) as rgba_dir:
        for _ in map_on_cores(lambda n: _write_frame(n, read_image(ws.images_dir / n), masks.get(n), masks_dir,
                                                     rgba_dir), names, "segment: writing masks and RGBA"):
            pass
    return _finish(ws, names, masks, per_frame, excluded, info, backend, cfg, time.perf_counter() - t0)


def _sam2(ws: Workspace, names: list[str], parts: dict, cfg: SegmentConfig):
    ckpt = check_sam2(cfg.sam2_checkpoint)
    config = resolve_config(ckpt, cfg.sam2_config)
    posed = [n for n in names if n in parts]
    out, sam_info = sam2_segment([ws.images_dir / n for n in posed], [parts[n] for n in posed], ckpt, config,
                                 device=cfg.device)
    return dict(zip(posed, out)), {"checkpoint": str(ckpt.resolve()), "config": config, **sam_info}


def _frame_rows(ws: Workspace, names: list[str], masks: dict[str, np.ndarray], facts: dict[str, dict], info: dict,
                cfg: SegmentConfig) -> tuple[list[dict], list[dict]]:
    """``segment.json``'s row of every frame and the frames without a plant; raises :class:`PlantsplatError` when
    more than ``cfg.max_excluded`` of them have none."""
    per_frame, excluded = [], []
    for n in names:
        m = masks.get(n)
        share = round(float(m.mean()), FRACTION_DIGITS) if m is not None else 0.0
        row = {"name": n, "foreground_fraction": share, **facts.get(n, {})}
        per_frame.append(row)
        if m is None or row["foreground_fraction"] < cfg.min_plant_fraction:
            reason = row.get("note") or f"no plant found (the mask covers {row['foreground_fraction']:.4%} of the frame)"
            excluded.append({"name": n, "reason": reason})
    if len(excluded) > cfg.max_excluded * len(names):
        raise PlantsplatError(
            f"{ws.images_dir}: no plant in {len(excluded)} of {len(names)} frames (e.g. {excluded[0]['name']}: "
            f"{excluded[0]['reason']}); " + ("the camera model has no 3D points (an imported model without points3D?), "
                                            "so the quick 3D model started from random ones: run the poses stage's "
                                            "SfM, or pass --import-masks DIR" if info.get("sfm_points") == 0 else
                                            "check the capture and the poses") + "; nothing was written")
    return per_frame, excluded


def _finish(ws: Workspace, names: list[str], masks: dict[str, np.ndarray], per_frame: list[dict], excluded: list[dict],
            info: dict, backend: str, cfg: SegmentConfig, seconds: float) -> dict:
    """The preview and ``segment.json`` (the masks and RGBA frames are written); returns ``segment.json``'s content."""
    shape = next(iter(masks.values())).shape if masks else read_image(ws.images_dir / names[0], "gray").shape
    conf = [r["confidence"] for r in per_frame if r.get("confidence") is not None]
    fg = [r["foreground_fraction"] for r in per_frame]
    out = {
        "backend": backend, "version": SEGMENT_VERSION,
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(cfg).items()},
        "image_size": [shape[1], shape[0]], "capture": info,
        "timing": {"total_s": round(seconds, 2), "seconds_per_frame": round(seconds / len(names), 4),
                   **info.pop("timing", {})},
        "foreground_fraction": {"mean": round(float(np.mean(fg)), FRACTION_DIGITS),
                                "min": round(float(np.min(fg)), FRACTION_DIGITS),
                                "max": round(float(np.max(fg)), FRACTION_DIGITS)},
        "confidence": ({"mean": round(float(np.mean(conf)), 4), "min": round(float(np.min(conf)), 4),
                        "least_sure": min((r for r in per_frame if r.get("confidence") is not None),
                                          key=lambda r: r["confidence"])["name"]} if conf else None),
        "excluded": excluded,
        "frames": per_frame,
    }
    if cfg.preview:
        _preview(ws, names, per_frame, {e["name"] for e in excluded})
        out["preview"] = ws.masks_preview_png.name
    write_json_atomic(ws.segment_json, out)
    log.info("segment: wrote %d masks (%s), mean foreground %.1f%%%s, %.2f s per frame", len(names), backend,
             100 * out["foreground_fraction"]["mean"],
             f", confidence {out['confidence']['mean']:.2f} (least sure {out['confidence']['min']:.2f})" if conf else "",
             out["timing"]["seconds_per_frame"])
    return out


def _write_frame(name: str, rgb: np.ndarray, mask: np.ndarray | None, masks_dir: Path, rgba_dir: Path) -> None:
    """One frame's mask (all background when it has none) and its RGBA image (``rgb``: the frame), under its name."""
    m8 = mask.astype(np.uint8) * 255 if mask is not None else np.zeros(rgb.shape[:2], np.uint8)
    _write_png(masks_dir / name, m8)
    _write_png(rgba_dir / name, np.dstack([rgb[..., ::-1], m8]))


def _preview(ws: Workspace, names: list[str], per_frame: list[dict], excluded: set[str]) -> None:
    """The contact sheet: the least sure frames first, then frames spread over the capture."""
    sure = [r.get("confidence") for r in per_frame]
    order = sorted(range(len(names)), key=lambda i: (sure[i] is None, sure[i] if sure[i] is not None else 1.0))
    pick = order[:PREVIEW_LEAST_SURE] + [int(i) for i in np.linspace(0, len(names) - 1, PREVIEW_SPREAD).round()]
    pick = list(dict.fromkeys(pick))[:PREVIEW_TILES]
    labels = [names[i] + (f"  sure {sure[i]:.2f}" if sure[i] is not None else "") for i in pick]
    sheet = contact_sheet([ws.images_dir / names[i] for i in pick], [ws.masks_dir / names[i] for i in pick],
                          labels=labels, excluded=[names[i] in excluded for i in pick], max_tiles=len(pick))
    write_image_atomic(ws.masks_preview_png, sheet)

"""Foreground segmentation (plant + cube) of a workspace's frames: masks, RGBA images, preview.

Backends:

- ``classic`` (default): offline, model-free; plant colour models, the cube's exact silhouette from
  its markers and a multi-view visual hull that tells the plant from green things elsewhere
  (:mod:`plantsplat.segment.classic`).
- ``sam2``: SAM-2's video predictor prompted on key frames with boxes and points taken from the
  classic result, propagated through the frames (:mod:`plantsplat.segment.sam2_backend`). Needs the
  ``sam2`` package and a checkpoint file.

Outputs (see :class:`plantsplat.workspace.Workspace`): ``masks/frame_*.png`` (uint8, 255 = plant or
cube), ``rgba/frame_*.png`` (alpha = mask), ``segment.json`` (backend, settings, per-frame foreground
fraction, excluded frames with reasons) and ``masks_preview.png`` (contact sheet).

Example:
    >>> from plantsplat.segment import segment_workspace
    >>> info = segment_workspace("ws/plant01")
    >>> info["backend"], len(info["frames"])
    ('classic', 120)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.io import atomic_path, png_params, read_image, read_json, write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, progress
from plantsplat.workspace import Workspace

log = get_logger(__name__)

SEGMENT_VERSION = 1
PREVIEW_NAME = "masks_preview.png"


_CACHE_BYTES = 768 * 2**20


def _write_png(path: Path, img: np.ndarray) -> None:
    """Write a gray or BGR(A) uint8 image as PNG atomically, with fast compression (:func:`plantsplat.io.png_params`)."""
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img, png_params()):
            raise PlantsplatError(f"{path}: could not write image; check the disk space and permissions")


def mask_iou(a, b) -> float:
    """Intersection over union of two bool masks of one shape (numpy arrays or torch tensors); 0 when both are empty.

    Example:
        >>> import numpy as np
        >>> mask_iou(np.array([True, True, False]), np.array([True, False, False]))
        0.5
    """
    union = float((a | b).sum())
    return float((a & b).sum()) / union if union > 0 else 0.0


def preview_path(ws: Workspace) -> Path:
    """Where the mask contact sheet goes: ``WS/masks_preview.png``."""
    return ws.root / PREVIEW_NAME


def _images_fingerprint(ws: Workspace, names: list[str]) -> str:
    """Hash of frames.json when present, else of the image names, sizes and times."""
    h = hashlib.sha1()
    if ws.frames_json.is_file():
        h.update(ws.frames_json.read_bytes())
    for n in names:
        st = (ws.images_dir / n).stat()
        h.update(f"{n}:{st.st_size}:{int(st.st_mtime)}".encode())
    return h.hexdigest()[:16]


def _settings_dict(settings) -> dict[str, Any]:
    def conv(x):
        if dataclasses.is_dataclass(x):
            return {f.name: conv(getattr(x, f.name)) for f in dataclasses.fields(x) if not f.name.startswith("_")}
        if isinstance(x, (tuple, list)):
            return [conv(v) for v in x]
        if isinstance(x, Path):
            return str(x)
        return x

    return conv(settings)


def _up_to_date(ws: Workspace, names: list[str], backend: str, settings: dict, fp: str) -> dict | None:
    if not ws.segment_json.is_file():
        return None
    try:
        old = read_json(ws.segment_json)
    except PlantsplatError:
        return None
    if old.get("backend") != backend or old.get("settings") != json.loads(json.dumps(settings)) or old.get("images_fingerprint") != fp:
        return None
    if not all((ws.masks_dir / n).is_file() and (ws.rgba_dir / n).is_file() for n in names):
        return None
    return old


def segment_workspace(
    ws: Workspace | str | os.PathLike,
    backend: str = "classic",
    force: bool = False,
    sam2_checkpoint: str | os.PathLike | None = None,
    sam2_config: str | None = None,
    settings=None,
    max_excluded: float = 0.5,
    min_plant_fraction: float = 5e-4,
    preview: bool = True,
    device: str | None = None,
    sam2_image_size: int | None = None,
) -> dict[str, Any]:
    """Segment every frame in ``ws/images`` into plant + cube; write masks, RGBA and a preview.

    Args:
        ws: the workspace (after ``plantsplat frames``).
        backend: ``"classic"`` or ``"sam2"``.
        force: recompute even if ``segment.json`` says the masks are up to date.
        sam2_checkpoint: SAM-2 checkpoint file (``{"model": state_dict}``), for ``backend="sam2"``.
        sam2_config: SAM-2 model config name (default: guessed from the checkpoint's name, e.g.
            ``configs/sam2.1/sam2.1_hiera_t.yaml`` for ``sam2.1_hiera_tiny.pt``).
        settings: :class:`plantsplat.segment.classic.ClassicSettings` (default settings when None).
        max_excluded: more than this fraction of frames without a plant is an error (nothing is written).
        min_plant_fraction: a frame whose plant covers less than this fraction of the image is
            excluded (listed in ``segment.json`` under ``excluded``; its mask is still written).
        preview: write ``masks_preview.png``.
        device: torch device for SAM-2 (default: CUDA when available, else CPU).
        sam2_image_size: override SAM-2's input size (tests of the plumbing only; default 1024).

    Returns:
        The content of ``segment.json``.

    Example:
        >>> info = segment_workspace("ws/plant01", backend="classic")
        >>> [e["name"] for e in info["excluded"]]
        []
    """
    import cv2

    from plantsplat.segment.classic import ClassicSegmenter, ClassicSettings, thread_map

    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    if backend not in ("classic", "sam2"):
        raise UsageError(f"unknown segmentation backend {backend!r}; use classic or sam2")
    if not ws.images_dir.is_dir():
        raise PlantsplatError(f"{ws.images_dir}: missing; run `plantsplat frames VIDEO --out {ws.root}` first")
    names = ws.image_names()
    if not names:
        raise PlantsplatError(f"{ws.images_dir}: no images; run `plantsplat frames VIDEO --out {ws.root}` first")
    settings = settings or ClassicSettings()
    sdict = {"classic": _settings_dict(settings), "min_plant_fraction": min_plant_fraction, "version": SEGMENT_VERSION}
    if backend == "sam2":
        from plantsplat.segment.sam2_backend import check_sam2, resolve_config

        ckpt = check_sam2(sam2_checkpoint)
        cfg_name = resolve_config(ckpt, sam2_config)
        sdict["sam2"] = {"checkpoint": str(ckpt.resolve()), "config": cfg_name}
    fp = _images_fingerprint(ws, names)
    if not force:
        old = _up_to_date(ws, names, backend, sdict, fp)
        if old is not None:
            log.info("%s: masks are up to date (%s backend); pass --force to redo", ws.root, backend)
            return old

    paths = [ws.images_dir / n for n in names]
    t0 = time.perf_counter()
    seg = ClassicSegmenter(settings)
    markers = None
    if ws.markers_json.is_file():
        from plantsplat.markers import read_markers

        markers = read_markers(ws.markers_json).frames
    ctx = seg.analyse(paths, keep_bytes=_CACHE_BYTES, markers=markers)  # frames within the budget stay decoded
    t_analyse = time.perf_counter() - t0
    masks: list[np.ndarray] = []
    parts: list[tuple[np.ndarray, np.ndarray]] = []  # packed (plant, cube) for SAM-2 prompts
    per_frame: list[dict[str, Any]] = []
    shape = None

    def one(i: int):
        rgb = seg.frames.get(i)
        if rgb is None:
            rgb = read_image(paths[i])
        plant, cube, info = seg.mask_parts(i, rgb, ctx)
        return rgb.shape[:2], plant, cube, info

    for i, (shape, plant, cube, info) in enumerate(progress(thread_map(one, range(len(paths))),
                                                             "segment: classic masks", total=len(paths))):
        masks.append(np.packbits(plant | cube, axis=None))
        if backend == "sam2":
            parts.append((np.packbits(plant, axis=None), np.packbits(cube, axis=None)))
        per_frame.append({"name": names[i], **{k: (round(v, 5) if isinstance(v, float) else v) for k, v in info.items()}})
    t_classic = time.perf_counter() - t0
    timing = {"classic_analyse_s": round(t_analyse, 3), "classic_total_s": round(t_classic, 3)}

    if backend == "sam2":
        from plantsplat.segment.sam2_backend import sam2_segment

        t1 = time.perf_counter()
        H, W = shape
        def unpack(b):
            return np.unpackbits(b, count=H * W).reshape(H, W).astype(bool)

        sam_masks, sam_info = sam2_segment(paths, [(unpack(a), unpack(b)) for a, b in parts], ckpt, cfg_name,
                                           device=device, image_size=sam2_image_size)
        masks = [np.packbits(m, axis=None) for m in sam_masks]
        for rec, m in zip(per_frame, sam_masks):
            rec["classic_foreground_fraction"] = rec["foreground_fraction"]
            rec["foreground_fraction"] = round(float(m.mean()), 5)
        timing["sam2_s"] = round(time.perf_counter() - t1, 3)
        sdict["sam2"].update(sam_info)

    # frames without a plant
    excluded = [
        {"name": r["name"], "reason": f"no plant found (plant covers {r['plant_fraction']:.4%} of the frame)"}
        for r in per_frame
        if r["plant_fraction"] < min_plant_fraction
    ]
    if excluded and len(excluded) > max_excluded * len(names):
        raise PlantsplatError(
            f"{ws.images_dir}: no plant found in {len(excluded)} of {len(names)} frames "
            f"(e.g. {', '.join(e['name'] for e in excluded[:3])}); check the capture (is the plant in view and green?) "
            "or try --backend sam2; nothing was written"
        )
    if excluded:
        log.warning("segment: no plant found in %d frame(s), excluded: %s", len(excluded),
                    ", ".join(e["name"] for e in excluded[:12]) + (" ..." if len(excluded) > 12 else ""))

    H, W = shape

    def write(i: int) -> None:
        m = np.unpackbits(masks[i], count=H * W).reshape(H, W).astype(bool)
        m8 = m.astype(np.uint8) * 255
        _write_png(ws.masks_dir / names[i], m8)
        rgb = seg.frames.pop(i, None)
        bgr = cv2.cvtColor(read_image(paths[i]) if rgb is None else rgb, cv2.COLOR_RGB2BGR)
        _write_png(ws.rgba_dir / names[i], cv2.merge([*cv2.split(bgr), m8]))  # BGRA [H, W, 4]

    for _ in progress(thread_map(write, range(len(paths))), "segment: writing masks and RGBA", total=len(paths)):
        pass
    # stale outputs of an earlier, different set of frames
    keep = set(names)
    for d in (ws.masks_dir, ws.rgba_dir):
        for f in d.iterdir():
            if f.name not in keep and re.fullmatch(r"frame_\d{5}\.png", f.name):
                f.unlink(missing_ok=True)

    fg = [r["foreground_fraction"] for r in per_frame]
    out = {
        "backend": backend,
        "settings": sdict,
        "images_fingerprint": fp,
        "image_size": [W, H],
        "capture": {k: v for k, v in ctx.info.items()},
        "intrinsics_K": ctx.K.round(4).tolist() if ctx.K is not None else None,
        "timing": {**timing, "seconds_per_frame": round((time.perf_counter() - t0) / len(names), 4)},
        "foreground_fraction": {"mean": round(float(np.mean(fg)), 5), "min": round(float(np.min(fg)), 5),
                                "max": round(float(np.max(fg)), 5)},
        "excluded": excluded,
        "frames": per_frame,
    }
    if preview:
        from plantsplat.segment.preview import contact_sheet

        excl = {e["name"] for e in excluded}
        sheet = contact_sheet(paths, [ws.masks_dir / n for n in names], labels=names,
                              excluded=[n in excl for n in names])
        write_image_atomic(preview_path(ws), sheet)
        out["preview"] = PREVIEW_NAME
    write_json_atomic(ws.segment_json, out)
    log.info("segment: wrote %d masks (%s), mean foreground %.1f%%, %.3f s per frame", len(names), backend,
             100 * out["foreground_fraction"]["mean"], out["timing"]["seconds_per_frame"])
    return out

"""The frames stage over a workspace: what it reads, what it writes, and :func:`run`.

A video (or image folder) becomes a set of sharp, spread-out frames in the workspace's ``images/``. The capture is
cut into ``num`` equal stretches (by source frame index); in each stretch the sharpest frame (variance of the
Laplacian of the luma, measured at half the working size for videos, at the working size for image folders) is
kept (:mod:`plantsplat.frames.select`, :mod:`plantsplat.frames.sources`). Frames far blurrier than the capture's
typical frame and near-duplicates of the previously kept frame (the camera stood still) are dropped. Kept frames are
rotated upright (the phone's display matrix), downscaled so the longer side is at most ``max_size`` and written as
``images/frame_00000.png``. ``frames.json`` records where each image came from.

Usage:
    from plantsplat.frames import FramesConfig, stage
    info = stage.run(Workspace("ws/plant01"), FramesConfig(num=120), "plant01.mp4")
    len(info["frames"]), info["working_size"]
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.frames.config import (
    ADVISED_FRAMES,
    ADVISED_SHORT_SIDE,
    FRAMES_VERSION,
    IMAGE_SUFFIXES,
    LOGGED_ITEMS,
    MIN_MAX_SIZE,
    FramesConfig,
)
from plantsplat.frames.select import drop_blurred_and_duplicates
from plantsplat.frames.sources import select_from_folder, select_from_video
from plantsplat.io import staged_dir, write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, make_progress
from plantsplat.workspace import IMAGE_PATTERN, Workspace

log = get_logger(__name__)


def inputs(ws: Workspace, source: str | os.PathLike) -> list[Path]:
    """The files the stage reads: the video or image folder."""
    return [Path(source)]


def outputs(ws: Workspace) -> list[Path]:
    """The files and folders the stage writes."""
    return [ws.images_dir, ws.frames_json]


def source_fingerprint(path: Path) -> dict[str, Any]:
    """The video's path, size and modification time (recorded in ``frames.json``)."""
    st = path.stat()
    return {"path": str(path.resolve()), "size_bytes": st.st_size, "mtime": int(st.st_mtime)}


def shortfalls(n_frames: int, width: int, height: int) -> list[str]:
    """What a capture of ``n_frames`` frames of ``width`` x ``height`` lacks against what registration needs.

    Example:
        >>> shortfalls(90, 270, 480)[1]
        'frames of 270x480 px: the short side should be at least 480 px (film at 1080p or more)'
        >>> shortfalls(120, 540, 960)
        []
    """
    out = []
    if n_frames < ADVISED_FRAMES:
        out.append(f"{n_frames} frames: a capture needs at least {ADVISED_FRAMES} (three slow rings, 6-12 degrees "
                   "between frames)")
    if min(width, height) < ADVISED_SHORT_SIDE:
        out.append(f"frames of {width}x{height} px: the short side should be at least {ADVISED_SHORT_SIDE} px "
                   "(film at 1080p or more)")
    return out


def check_not_inside(src: Path, ws: Workspace) -> None:
    """Refuse an input that is, holds or lies inside ``images/``, the folder the stage replaces."""
    out_dir, src = ws.images_dir.resolve(), Path(src).resolve()
    if src == out_dir or out_dir in src.parents or src in out_dir.parents:
        raise UsageError(f"{src}: is (or holds) {ws.images_dir}, the folder this stage writes; copy your images to "
                         "another folder and pass that one (your images are left as they are)")


def run(ws: Workspace | str | os.PathLike, cfg: FramesConfig | None, source: str | os.PathLike) -> dict[str, Any]:
    """Run the frames stage: choose ``cfg.num`` sharp frames spread over ``source`` and write them to ``ws``.

    ``source``: a video file (mp4/mov/..., H.264 or HEVC; rotation metadata honoured) or a folder of
    images (never inside the workspace's ``images/``, which this stage replaces whole when it is done).
    See :class:`FramesConfig` for the options. Returns the content of ``frames.json``.

    Usage:
        info = run("ws/plant", FramesConfig(num=100), "plant.mov")
        info["frames"][0]["name"], info["kind"]
    """
    cfg = cfg or FramesConfig()
    num, max_size, min_frames = cfg.num, cfg.max_size, cfg.min_frames
    blur_ratio, dup_threshold = cfg.blur_ratio, cfg.dup_threshold
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    src = Path(source)
    if num < 1:
        raise UsageError(f"the frame count (--num; --frames.num for `run`) must be at least 1, got {num}")
    if max_size < MIN_MAX_SIZE:
        raise UsageError(f"the image size (--max-size; --frames.max-size for `run`) must be at least {MIN_MAX_SIZE} px, "
                         f"got {max_size}")
    if not src.exists():
        raise PlantsplatError(f"{src}: no such file or folder; pass a video file or a folder of images")
    kind = "folder" if src.is_dir() else "video"
    if kind == "video" and src.suffix.lower() in IMAGE_SUFFIXES:
        raise PlantsplatError(f"{src}: is a single image; pass a video or a folder of images")
    settings = {"num": num, "max_size": max_size, "min_frames": min_frames, "blur_ratio": blur_ratio,
                "dup_threshold": dup_threshold, "version": FRAMES_VERSION}
    fingerprint = source_fingerprint(src) if kind == "video" else {"path": str(src.resolve())}
    check_not_inside(src, ws)

    log.info("frames: choosing up to %d frames from %s", num, src)
    if kind == "video":
        cands, info = select_from_video(src, num, max_size)
    else:
        cands, info = select_from_folder(src, num, max_size)
    kept, dropped = drop_blurred_and_duplicates(cands, blur_ratio, dup_threshold)
    if dropped:
        most = LOGGED_ITEMS[0]
        log.warning("frames: dropped %d frame(s): %s", len(dropped),
                    "; ".join(f"#{d['source_index']}: {d['reason']}" for d in dropped[:most])
                    + (" ..." if len(dropped) > most else ""))
    if len(kept) < min_frames:
        raise PlantsplatError(
            f"{src}: only {len(kept)} usable frames (of {info['total_source_frames']}; at least {min_frames} needed); "
            "record a longer, steadier video or add images"
        )

    records = []
    with staged_dir(ws.images_dir) as tmp, make_progress() as bar:  # images/ is replaced whole, when finished
        task = bar.add_task("writing images", total=len(kept), info="")
        for i, c in enumerate(kept):
            name = IMAGE_PATTERN.format(i)
            write_image_atomic(tmp / name, c["rgb"])
            rec = {"name": name, "source_index": int(c["source_index"]), "sharpness": round(float(c["sharpness"]), 3)}
            if "source_name" in c:
                rec["source_name"] = c["source_name"]
            if info.get("fps"):
                rec["time_s"] = round(c["source_index"] / info["fps"], 4)
            records.append(rec)
            bar.advance(task)
    out = {
        "source": fingerprint,
        "kind": kind,
        "rotation": info["rotation"],
        "source_size": info["source_size"],
        "working_size": info["working_size"],
        "total_source_frames": info["total_source_frames"],
        "header_frames": info.get("header_frames"),
        "fps": info.get("fps"),
        "settings": settings,
        "median_sharpness_all": round(info["median_sharpness_all"], 3),
        "dropped": dropped,
        "unreadable": info.get("unreadable", []),
        "frames": records,
        "shortfalls": shortfalls(len(records), *info["working_size"]),
    }
    for line in out["shortfalls"]:
        log.warning("capture: %s; poses may fail (see the README, 'Film it')", line)
    write_json_atomic(ws.frames_json, out)
    log.info("frames: wrote %d images (%dx%d) to %s", len(records), *info["working_size"], ws.images_dir)
    return out

"""Video (or image folder) -> a set of sharp, spread-out frames in a workspace's ``images/``.

The capture is cut into ``num`` equal stretches (by source frame index); in each stretch the
sharpest frame (variance of the Laplacian of the luma, measured at half the working size for
videos, at the working size for image folders) is kept.
Frames far blurrier than the capture's typical frame and near-duplicates of the previously kept
frame (the camera stood still) are dropped. Kept frames are rotated upright (the phone's display
matrix), downscaled so the longer side is at most ``max_size`` and written as
``images/frame_00000.png``. ``frames.json`` records where each image came from.

Decoding is done with PyAV (FFmpeg's decoders, frame threads on); nothing is decoded twice and only
the best candidate of the current stretch is kept in memory as a decoded frame.

Usage:
    info = extract_frames("plant01.mp4", Workspace("ws/plant01"), FramesConfig(num=120))
    len(info["frames"]), info["working_size"]
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.io import imread_quietly, staged_dir, write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, make_progress
from plantsplat.workspace import IMAGE_PATTERN, Workspace

log = get_logger(__name__)

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts", ".3gp"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
FRAMES_VERSION = 1

ADVISED_FRAMES = 100
"""Fewer frames than this (three rings of about 40, 6-12 degrees apart) register poorly: a 90-frame capture at
270x480 did not register at all (2026-11-26)."""
ADVISED_SHORT_SIDE = 480
"""Frames narrower than this (px, short side) give too few SIFT features on blank rooms (540x960 is what the
benchmarks use; 270x480 did not register)."""


@dataclass
class FramesConfig:
    """Options of the frames stage."""

    num: int = 120
    """Number of frames to aim for (the paper used 100-150): one per equal stretch of the capture."""
    max_size: int = 960
    """Longest side of the written images in pixels (1/4 of 4K = 960); never upscaled."""
    min_frames: int = 8
    """Fewer usable frames than this is an error."""
    blur_ratio: float = 0.35
    """Drop a chosen frame whose sharpness is below this fraction of the median chosen frame."""
    dup_threshold: float = 1.0
    """Drop a frame whose 64-px thumbnail differs from the previous kept one by less than this (0-255)."""


# --------------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------------
def working_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """Size ``(w, h)`` after downscaling so that the longer side is at most ``max_size`` (never upscaled).

    Example:
        >>> working_size(1080, 1920, 960)
        (540, 960)
    """
    scale = min(1.0, float(max_size) / max(width, height))
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a gray image ``[H, W]`` (higher = sharper).

    Example:
        >>> import numpy as np
        >>> sharpness(np.zeros((8, 8), np.uint8))
        0.0
    """
    import cv2

    lap = cv2.Laplacian(gray, cv2.CV_32F, ksize=3)
    return float(lap.var())


def _thumb(gray: np.ndarray) -> np.ndarray:
    """A 64-pixel-wide float thumbnail used to spot near-duplicates. ``[h, 64]``."""
    import cv2

    h, w = gray.shape
    tw = 64
    th = max(1, int(round(h * tw / w)))
    return cv2.resize(gray, (tw, th), interpolation=cv2.INTER_AREA).astype(np.float32)


def _rotate(img: np.ndarray, degrees_ccw: int) -> np.ndarray:
    """Rotate an image counter-clockwise by a multiple of 90 degrees (display-matrix convention)."""
    k = int(round(degrees_ccw / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(img, k=k)) if k else img


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _source_fingerprint(path: Path) -> dict[str, Any]:
    st = path.stat()
    return {"path": str(path.resolve()), "size_bytes": st.st_size, "mtime": int(st.st_mtime)}


def _segments(total: int, num: int) -> np.ndarray:
    """Stretch index of each source index when ``total`` frames are cut into ``num`` stretches. ``[total]``."""
    return (np.arange(total, dtype=np.int64) * num) // total


def _luma(frame) -> np.ndarray:
    """The Y plane of a decoded PyAV frame as uint8 ``[H, W]`` (no colour conversion when planar YUV)."""
    fmt = frame.format
    name = fmt.name
    if (name.startswith("yuv") or name.startswith("yuvj") or name.startswith("nv")) and not fmt.is_rgb:
        plane = frame.planes[0]
        bits = fmt.components[0].bits
        if bits <= 8:
            buf = np.frombuffer(plane, np.uint8).reshape(plane.height, plane.line_size)
            return buf[:, : plane.width]
        buf = np.frombuffer(plane, np.uint16).reshape(plane.height, plane.line_size // 2)
        return (buf[:, : plane.width] >> (bits - 8)).astype(np.uint8)
    return frame.to_ndarray(format="gray")


# --------------------------------------------------------------------------------------------------
# selection shared by videos and folders
# --------------------------------------------------------------------------------------------------
class _Selector:
    """Keeps the sharpest candidate of each stretch; candidates are pushed in source order."""

    def __init__(self, total: int, num: int, size: tuple[int, int]):
        self.seg_of = _segments(total, num)
        self.size = size  # (w, h) working size, after rotation
        self.best: dict[int, tuple[float, int, Any]] = {}
        self.done: list[dict[str, Any]] = []
        self.all_sharpness: list[float] = []

    def push(self, index: int, gray_small: np.ndarray, payload: Any, finish) -> None:
        s = sharpness(gray_small)
        self.all_sharpness.append(s)
        seg = int(self.seg_of[min(index, len(self.seg_of) - 1)])
        cur = self.best.get(seg)
        if cur is None or s > cur[0]:
            self.best[seg] = (s, index, payload)
        # stretches before this one are complete: finish them (decode/convert only the winner)
        for k in [k for k in self.best if k < seg]:
            self._finish(k, finish)

    def _finish(self, seg: int, finish) -> None:
        s, index, payload = self.best.pop(seg)
        rgb = finish(payload)
        self.done.append({"source_index": index, "sharpness": s, "rgb": rgb, "payload_info": payload})

    def close(self, finish) -> list[dict[str, Any]]:
        for k in sorted(self.best):
            self._finish(k, finish)
        return sorted(self.done, key=lambda d: d["source_index"])


def _filter(cands: list[dict[str, Any]], blur_ratio: float, dup_threshold: float) -> tuple[list, list]:
    """Drop blurred frames and near-duplicates. Returns ``(kept, dropped)``; ``dropped`` has reasons."""
    import cv2

    if not cands:
        return [], []
    ref = float(np.median([c["sharpness"] for c in cands]))
    kept, dropped = [], []
    prev_thumb = None
    for c in cands:
        gray = cv2.cvtColor(c["rgb"], cv2.COLOR_RGB2GRAY)
        thumb = _thumb(gray)
        if ref > 0 and c["sharpness"] < blur_ratio * ref:
            dropped.append({"source_index": c["source_index"],
                            "reason": f"blurred (sharpness {c['sharpness']:.1f} < {blur_ratio} x median {ref:.1f})"})
            continue
        if prev_thumb is not None and prev_thumb.shape == thumb.shape:
            diff = float(np.mean(np.abs(thumb - prev_thumb)))
            if diff < dup_threshold:
                dropped.append({"source_index": c["source_index"],
                                "reason": f"near-duplicate of the previous frame (mean difference {diff:.2f})"})
                continue
        prev_thumb = thumb
        kept.append(c)
    return kept, dropped


# --------------------------------------------------------------------------------------------------
# sources
# --------------------------------------------------------------------------------------------------
def _open_video(path: Path):
    import av

    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise PlantsplatError(f"{path}: cannot open the video ({exc}); re-export it as H.264/HEVC mp4 or mov") from exc
    if not container.streams.video:
        container.close()
        raise PlantsplatError(f"{path}: has no video stream; pass a video file or a folder of images")
    return container


def _count_video_frames(path: Path) -> int:
    """Number of frames in the first video stream (from the header, else by counting packets)."""
    container = _open_video(path)
    try:
        stream = container.streams.video[0]
        if stream.frames and stream.frames > 0:
            return int(stream.frames)
        n = 0
        for packet in container.demux(stream):
            if packet.size:
                n += 1
        return n
    except Exception as exc:  # a corrupt container fails while demuxing
        raise PlantsplatError(f"{path}: the video cannot be read ({type(exc).__name__}: {exc}); re-export it") from exc
    finally:
        container.close()


def _small_gray(frame, size: tuple[int, int], rotation: int):
    """The frame's luma at half the working ``size`` (sharpness is measured there: cheap, blur still shows), in the
    frame's own orientation (before ``rotation``)."""
    import cv2

    sw, sh = max(8, size[0] // 2), max(8, size[1] // 2)
    dsize = (sh, sw) if rotation in (90, 270) else (sw, sh)
    return cv2.resize(_luma(frame), dsize, interpolation=cv2.INTER_AREA)


def check_decoded(path: Path, said: list, damaged: list[int], decoded: int) -> None:
    """Refuse a video whose decoder reported errors within its frames (overwritten or damaged bytes: FFmpeg conceals
    them with grey and smeared blocks, which no later stage could tell from the scene). Errors only after the last
    frame are a truncated end, which the caller reports as such."""
    inside = sorted({i for i in damaged if i < decoded - 1})
    if inside:
        first = str(said[damaged.index(inside[0])][2]).strip()
        raise PlantsplatError(
            f"{path}: the video is damaged: the decoder reported errors in {len(inside)} frame(s) from frame "
            f"{inside[0]} on ({first}); its frames would be garbage, so this is the file's fault, not the filming: "
            "copy it from the phone again or re-export it")


def _select_from_video(path: Path, num: int, max_size: int) -> tuple[list, dict]:
    import av
    import cv2

    total = _count_video_frames(path)
    if total <= 0:
        raise PlantsplatError(f"{path}: the video has no frames; record or export it again")
    container = _open_video(path)
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"
    src_w, src_h = stream.codec_context.width, stream.codec_context.height
    meta_rotate = 0
    try:  # legacy 'rotate' tag: clockwise degrees
        meta_rotate = -int(stream.metadata.get("rotate", 0))
    except (TypeError, ValueError):
        meta_rotate = 0
    n_take = min(num, total)
    if total < num:
        log.warning("%s: only %d frames in the video, fewer than --num %d; using all of them", path, total, num)
    info: dict[str, Any] = {"rotation": None, "source_size": [src_w, src_h], "total_source_frames": total,
                            "fps": float(stream.average_rate) if stream.average_rate else None}
    sel = None
    decoded = 0

    def finish(frame):
        rgb = frame.to_ndarray(format="rgb24")
        rgb = _rotate(rgb, info["rotation"])
        w, h = sel.size
        if (rgb.shape[1], rgb.shape[0]) != (w, h):
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        return rgb

    level = av.logging.get_level()
    av.logging.set_level(av.logging.ERROR)  # the decoder's errors (damaged data) are counted, never printed raw
    damaged: list[int] = []  # frames during whose decoding the decoder reported an error
    try:
        with make_progress() as bar, av.logging.Capture(local=False) as said:
            task = bar.add_task(f"decoding {path.name}", total=total, info="")
            for frame in container.decode(stream):
                if len(said) > len(damaged):
                    damaged += [decoded] * (len(said) - len(damaged))
                if info["rotation"] is None:
                    rot = frame.rotation or meta_rotate
                    info["rotation"] = int(round(rot / 90.0)) * 90 % 360
                    w0, h0 = frame.width, frame.height
                    if info["rotation"] in (90, 270):
                        w0, h0 = h0, w0
                    sel = _Selector(total, n_take, working_size(w0, h0, max_size))
                sel.push(decoded, _small_gray(frame, sel.size, info["rotation"]), frame, finish)
                decoded += 1
                bar.advance(task)
    except av.error.FFmpegError as exc:
        if decoded == 0:
            raise PlantsplatError(f"{path}: no frame could be decoded ({exc}); re-export the video as H.264 mp4") from exc
        log.warning("%s: decoding stopped after %d of %d frames (%s); using what was decoded", path, decoded, total, exc)
    finally:
        container.close()
        av.logging.set_level(level)
    check_decoded(path, said, damaged, decoded)
    if decoded == 0 or sel is None:
        raise PlantsplatError(f"{path}: no frame could be decoded; re-export the video as H.264 mp4")
    if decoded < total:
        # the header over-counted, or the file is truncated: stretches past the end simply stay empty
        (log.warning if decoded < 0.9 * total else log.info)(
            "%s: decoded %d of the %d frames its header announces%s", path, decoded, total,
            "; the file looks truncated (re-export or copy it again if the capture was longer)" if decoded < 0.9 * total else "")
        info["total_source_frames"] = decoded
        info["header_frames"] = total
    cands = sel.close(finish)
    for c in cands:
        c.pop("payload_info", None)
    info["working_size"] = list(sel.size)
    info["median_sharpness_all"] = float(np.median(sel.all_sharpness))
    return cands, info


def _list_images(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _select_from_folder(folder: Path, num: int, max_size: int) -> tuple[list, dict]:
    import cv2

    files = _list_images(folder)
    if not files:
        looked = ", ".join(sorted(IMAGE_SUFFIXES))
        raise PlantsplatError(f"{folder}: no images found (looked for {looked}); pass a video or a folder of photos")
    total = len(files)
    n_take = min(num, total)
    if total < num:
        log.info("%s: %d images, fewer than --num %d; using all of them", folder, total, num)
    sel = None
    src_size = None
    unreadable = []

    def finish(rgb):
        return rgb

    with make_progress() as bar:
        task = bar.add_task(f"reading {folder.name}", total=total, info="")
        for i, p in enumerate(files):
            bar.advance(task)
            bgr = imread_quietly(p, cv2.IMREAD_COLOR)  # applies EXIF orientation
            if bgr is None:
                unreadable.append(p.name)
                continue
            h, w = bgr.shape[:2]
            if src_size is None:
                src_size = (w, h)
                sel = _Selector(total, n_take, working_size(w, h, max_size))
            elif (w, h) != src_size:
                raise PlantsplatError(
                    f"{p}: size {w}x{h} differs from the first image's {src_size[0]}x{src_size[1]}; "
                    "use images from one camera at one resolution and orientation"
                )
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            sw, sh = sel.size
            if (w, h) != (sw, sh):
                rgb = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA)
            sel.push(i, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), rgb, finish)
    if unreadable:
        log.warning("%s: skipped %d unreadable image(s): %s", folder, len(unreadable),
                    ", ".join(unreadable[:10]) + (" ..." if len(unreadable) > 10 else ""))
    if sel is None:
        raise PlantsplatError(f"{folder}: none of the {total} images could be read; check the files")
    cands = sel.close(finish)
    for c in cands:
        c["source_name"] = files[c["source_index"]].name
        c.pop("payload_info", None)
    info = {"rotation": 0, "source_size": list(src_size), "total_source_frames": total,
            "working_size": list(sel.size), "unreadable": unreadable,
            "median_sharpness_all": float(np.median(sel.all_sharpness))}
    return cands, info


# --------------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------------
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


def extract_frames(input: str | os.PathLike, ws: Workspace | str | os.PathLike, cfg: FramesConfig | None = None
                   ) -> dict[str, Any]:
    """Choose ``cfg.num`` sharp frames spread over a video or image folder and write them to ``ws``.

    ``input``: a video file (mp4/mov/..., H.264 or HEVC; rotation metadata honoured) or a folder of
    images (never inside the workspace's ``images/``, which this stage replaces whole when it is done).
    See :class:`FramesConfig` for the options. Returns the content of ``frames.json``.

    Usage:
        info = extract_frames("plant.mov", "ws/plant", FramesConfig(num=100))
        info["frames"][0]["name"], info["kind"]
    """
    cfg = cfg or FramesConfig()
    num, max_size, min_frames = cfg.num, cfg.max_size, cfg.min_frames
    blur_ratio, dup_threshold = cfg.blur_ratio, cfg.dup_threshold
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    src = Path(input)
    if num < 1:
        raise UsageError(f"the frame count (--num; --frames.num for `run`) must be at least 1, got {num}")
    if max_size < 16:
        raise UsageError(f"the image size (--max-size; --frames.max-size for `run`) must be at least 16 px, got {max_size}")
    if not src.exists():
        raise PlantsplatError(f"{src}: no such file or folder; pass a video file or a folder of images")
    kind = "folder" if src.is_dir() else "video"
    if kind == "video" and src.suffix.lower() in IMAGE_SUFFIXES:
        raise PlantsplatError(f"{src}: is a single image; pass a video or a folder of images")
    settings = {"num": num, "max_size": max_size, "min_frames": min_frames, "blur_ratio": blur_ratio,
                "dup_threshold": dup_threshold, "version": FRAMES_VERSION}
    fingerprint = _source_fingerprint(src) if kind == "video" else {"path": str(src.resolve())}
    check_not_inside(src, ws)

    log.info("frames: choosing up to %d frames from %s", num, src)
    if kind == "video":
        cands, info = _select_from_video(src, num, max_size)
    else:
        cands, info = _select_from_folder(src, num, max_size)
    kept, dropped = _filter(cands, blur_ratio, dup_threshold)
    if dropped:
        log.warning("frames: dropped %d frame(s): %s", len(dropped),
                    "; ".join(f"#{d['source_index']}: {d['reason']}" for d in dropped[:5]) + (" ..." if len(dropped) > 5 else ""))
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

"""Where frames come from: a video, decoded with PyAV (FFmpeg's decoders, frame threads on; nothing is decoded twice
and only the best candidate of the current stretch is kept in memory as a decoded frame), or a folder of images.

Both hand their candidates to :class:`plantsplat.frames.select.Selector`; video frames are rotated upright (the
phone's display matrix) and scaled to the working size.

Usage:
    cands, info = select_from_video(Path("plant01.mp4"), 120, 960)
    cands[0]["source_index"], cands[0]["rgb"].shape, info["rotation"]
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.frames.config import IMAGE_SUFFIXES, LOGGED_ITEMS, SHARPNESS_MIN_SIDE, TRUNCATED_SHARE
from plantsplat.frames.select import Selector, working_size
from plantsplat.io import imread_quietly
from plantsplat.log import get_logger, make_progress

log = get_logger(__name__)


def rotate(img: np.ndarray, degrees_ccw: int) -> np.ndarray:
    """Rotate an image counter-clockwise by a multiple of 90 degrees (display-matrix convention)."""
    k = int(round(degrees_ccw / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(img, k=k)) if k else img


def natural_key(name: str):
    """Sort key that orders ``img_2`` before ``img_10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def luma(frame) -> np.ndarray:
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


def open_video(path: Path):
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as exc:
        raise PlantsplatError(f"{path}: cannot open the video ({exc}); re-export it as H.264/HEVC mp4 or mov") from exc
    if not container.streams.video:
        container.close()
        raise PlantsplatError(f"{path}: has no video stream; pass a video file or a folder of images")
    return container


def count_video_frames(path: Path) -> int:
    """Number of frames in the first video stream (from the header, else by counting packets)."""
    container = open_video(path)
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


def small_gray(frame, size: tuple[int, int], rotation: int):
    """The frame's luma at half the working ``size`` (sharpness is measured there: cheap, blur still shows), in the
    frame's own orientation (before ``rotation``)."""
    sw, sh = max(SHARPNESS_MIN_SIDE, size[0] // 2), max(SHARPNESS_MIN_SIDE, size[1] // 2)
    dsize = (sh, sw) if rotation in (90, 270) else (sw, sh)
    return cv2.resize(luma(frame), dsize, interpolation=cv2.INTER_AREA)


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


def select_from_video(path: Path, num: int, max_size: int) -> tuple[list, dict]:
    """The sharpest frame of each of ``num`` stretches of the video, upright and at the working size, and what was
    learned of the video (rotation, sizes, frame count, fps)."""
    total = count_video_frames(path)
    if total <= 0:
        raise PlantsplatError(f"{path}: the video has no frames; record or export it again")
    container = open_video(path)
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
        rgb = rotate(rgb, info["rotation"])
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
                    sel = Selector(total, n_take, working_size(w0, h0, max_size))
                sel.push(decoded, small_gray(frame, sel.size, info["rotation"]), frame, finish)
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
        truncated = decoded < TRUNCATED_SHARE * total
        (log.warning if truncated else log.info)(
            "%s: decoded %d of the %d frames its header announces%s", path, decoded, total,
            "; the file looks truncated (re-export or copy it again if the capture was longer)" if truncated else "")
        info["total_source_frames"] = decoded
        info["header_frames"] = total
    cands = sel.close(finish)
    for c in cands:
        c.pop("payload_info", None)
    info["working_size"] = list(sel.size)
    info["median_sharpness_all"] = float(np.median(sel.all_sharpness))
    return cands, info


def list_images(folder: Path) -> list[Path]:
    """The images in ``folder`` (hidden files left out), in natural order."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def select_from_folder(folder: Path, num: int, max_size: int) -> tuple[list, dict]:
    """The sharpest image of each of ``num`` stretches of the folder, at the working size, and what was learned of
    the images (sizes, count, the unreadable ones)."""
    files = list_images(folder)
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
                sel = Selector(total, n_take, working_size(w, h, max_size))
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
        most = LOGGED_ITEMS[1]
        log.warning("%s: skipped %d unreadable image(s): %s", folder, len(unreadable),
                    ", ".join(unreadable[:most]) + (" ..." if len(unreadable) > most else ""))
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

"""`plantsplat frames`: video or image folder -> sharp, spread-out frames in WS/images/."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from plantsplat.commands import Command


@dataclass
class FramesConfig:
    """Choose sharp frames spread over a video (or image folder) and write them to WS/images/.

    Example: plantsplat frames plant01.mov --out ws/plant01 --num 120 --max-size 960
    """

    input: tyro.conf.Positional[Path]
    """Video file (mp4/mov, H.264 or HEVC; phone rotation honoured) or a folder of images."""
    out: Path
    """Workspace folder to write images/ and frames.json into (created if missing)."""
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
    force: bool = False
    """Re-extract even if this input was already extracted; replaces the images in WS/images/."""


def run(cfg: FramesConfig) -> int:
    from plantsplat.frames import extract_frames
    from plantsplat.workspace import Workspace

    extract_frames(
        cfg.input,
        Workspace(cfg.out),
        num=cfg.num,
        max_size=cfg.max_size,
        force=cfg.force,
        min_frames=cfg.min_frames,
        blur_ratio=cfg.blur_ratio,
        dup_threshold=cfg.dup_threshold,
    )
    return 0


COMMAND = Command(
    name="frames",
    config=FramesConfig,
    run=run,
    help="Video or image folder -> sharp frames spread over the capture (WS/images/).",
    order=20,
)

"""The frames stage's settings: :class:`FramesConfig` (its options, each a documented field) and the constants of
frame selection.

Example:
    >>> FramesConfig().num, FramesConfig(max_size=480).max_size
    (120, 480)
"""

from __future__ import annotations

from dataclasses import dataclass

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts", ".3gp"}
"""File endings taken as videos."""
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
"""File endings taken as images (of an image folder)."""
FRAMES_VERSION = 1
"""Version of ``frames.json``'s selection (its ``settings``)."""

ADVISED_FRAMES = 100
"""Fewer frames than this (three rings of about 40, 6-12 degrees apart) register poorly: a 90-frame capture at
270x480 did not register at all (2026-11-26)."""
ADVISED_SHORT_SIDE = 480
"""Frames narrower than this (px, short side) give too few SIFT features on blank rooms (540x960 is what the
benchmarks use; 270x480 did not register)."""
THUMB_WIDTH = 64
"""Width (px) of the thumbnails compared to spot near-duplicate frames (``FramesConfig.dup_threshold``)."""
SHARPNESS_MIN_SIDE = 8
"""A video frame's sharpness is measured at half the working size, but on at least this many pixels a side."""
TRUNCATED_SHARE = 0.9
"""A video whose decoded frames fall short of this share of those its header announces is said to be truncated."""
MIN_MAX_SIZE = 16
"""The smallest ``max_size`` (px) accepted."""
LOGGED_ITEMS = (5, 10)
"""Log messages name at most this many dropped frames and unreadable images."""


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

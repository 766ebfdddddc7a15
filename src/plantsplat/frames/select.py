"""Frame selection shared by videos and image folders: the capture cut into equal stretches, the sharpest frame of
each kept (:class:`Selector`), then blurred frames and near-duplicates dropped (:func:`drop_blurred_and_duplicates`).

Example:
    >>> import numpy as np
    >>> working_size(1080, 1920, 960), stretches(6, 3).tolist()
    ((540, 960), [0, 0, 1, 1, 2, 2])
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from plantsplat.frames.config import THUMB_WIDTH


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
    lap = cv2.Laplacian(gray, cv2.CV_32F, ksize=3)
    return float(lap.var())


def thumbnail(gray: np.ndarray) -> np.ndarray:
    """A :data:`THUMB_WIDTH`-pixel-wide float thumbnail used to spot near-duplicates. ``[h, THUMB_WIDTH]``."""
    h, w = gray.shape
    tw = THUMB_WIDTH
    th = max(1, int(round(h * tw / w)))
    return cv2.resize(gray, (tw, th), interpolation=cv2.INTER_AREA).astype(np.float32)


def stretches(total: int, num: int) -> np.ndarray:
    """Stretch index of each source index when ``total`` frames are cut into ``num`` stretches. ``[total]``."""
    return (np.arange(total, dtype=np.int64) * num) // total


class Selector:
    """Keeps the sharpest candidate of each stretch; candidates are pushed in source order."""

    def __init__(self, total: int, num: int, size: tuple[int, int]):
        self.seg_of = stretches(total, num)
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


def drop_blurred_and_duplicates(cands: list[dict[str, Any]], blur_ratio: float, dup_threshold: float) -> tuple[list, list]:
    """Drop blurred frames and near-duplicates. Returns ``(kept, dropped)``; ``dropped`` has reasons."""
    if not cands:
        return [], []
    ref = float(np.median([c["sharpness"] for c in cands]))
    kept, dropped = [], []
    prev_thumb = None
    for c in cands:
        gray = cv2.cvtColor(c["rgb"], cv2.COLOR_RGB2GRAY)
        thumb = thumbnail(gray)
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

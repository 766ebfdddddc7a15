"""Mask overlay contact sheet: a grid of frames with the background dimmed and the mask outlined.

Usage:
    from plantsplat.segment.preview import contact_sheet
    sheet = contact_sheet(["ws/images/frame_00000.png"], ["ws/masks/frame_00000.png"])  # [H, W, 3] uint8
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import cv2
import numpy as np

from plantsplat.io import read_image

BACKGROUND_TINT = (40, 40, 120)
"""RGB colour the background is blended towards (a dim blue)."""
BACKGROUND_KEEP = 0.35
"""Share of the frame's own colour the background keeps ..."""
TINT_SHARE = 0.65
"""... and share of :data:`BACKGROUND_TINT` in it."""
OUTLINE_COLOUR = (255, 230, 0)
"""RGB colour of the mask's outline (yellow)."""
OUTLINE_PX_PER = 400
"""The outline is one pixel wide per this many pixels of the frame's longer side (at least one)."""
MASK_THRESHOLD = 127
"""A pixel of a mask resized to the tile is inside the mask above this (of 255)."""
LABEL_BAR_PX = 18
"""Height of the black bar behind a tile's label (pixels)."""
LABEL_ORIGIN = (4, 13)
"""Where a tile's label starts: x and the text's baseline y (pixels)."""
LABEL_FONT_SCALE = 0.42
"""OpenCV font scale of a tile's label."""


def overlay(rgb: np.ndarray, mask: np.ndarray, excluded: bool = False) -> np.ndarray:
    """Frame ``[H, W, 3]`` with the background dimmed and tinted and the mask's outline drawn."""
    m = mask > 0 if mask.dtype != bool else mask
    out = rgb.astype(np.float32)
    tint = np.array(BACKGROUND_TINT, np.float32)
    out[~m] = BACKGROUND_KEEP * out[~m] + TINT_SHARE * tint
    out = np.clip(out, 0, 255).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    t = max(1, round(max(rgb.shape[:2]) / OUTLINE_PX_PER))
    cv2.drawContours(out, contours, -1, OUTLINE_COLOUR, t, lineType=cv2.LINE_AA)
    if excluded:
        cv2.line(out, (0, 0), (out.shape[1] - 1, out.shape[0] - 1), (255, 0, 0), 2 * t)
    return out


def contact_sheet(
    images: Sequence[str | os.PathLike],
    masks: Sequence[str | os.PathLike | np.ndarray | None],
    labels: Sequence[str] | None = None,
    excluded: Sequence[bool] | None = None,
    max_tiles: int = 16,
    tile_height: int = 320,
    columns: int = 4,
) -> np.ndarray:
    """A contact sheet of up to ``max_tiles`` frames spread over the capture, masks overlaid (a frame whose
    mask is None is shown as it is).

    Returns an RGB uint8 image ``[rows * tile_height (+ labels), columns * tile_width, 3]``.
    """
    n = len(images)
    if n == 0:
        raise ValueError("no images for the contact sheet")
    pick = np.unique(np.linspace(0, n - 1, min(max_tiles, n)).round().astype(int))
    tiles = []
    for k in pick:
        rgb = read_image(images[k])
        mk = masks[k]
        h, w = rgb.shape[:2]
        tw = max(1, round(w * tile_height / h))
        # overlay at the tile's size (a full-size overlay was most of the sheet's time)
        tile = cv2.resize(rgb, (tw, tile_height), interpolation=cv2.INTER_AREA)
        if mk is not None:
            m = mk if isinstance(mk, np.ndarray) else read_image(mk, mode="gray")
            m_small = cv2.resize((m > 0).astype(np.uint8) * 255, (tw, tile_height), interpolation=cv2.INTER_AREA) > MASK_THRESHOLD
            tile = overlay(tile, m_small, bool(excluded[k]) if excluded is not None else False)
        text = labels[k] if labels is not None else str(k)
        cv2.rectangle(tile, (0, 0), (tw, LABEL_BAR_PX), (0, 0, 0), -1)
        cv2.putText(tile, text, LABEL_ORIGIN, cv2.FONT_HERSHEY_SIMPLEX, LABEL_FONT_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    tw = max(t.shape[1] for t in tiles)
    tiles = [np.pad(t, ((0, 0), (0, tw - t.shape[1]), (0, 0))) for t in tiles]
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    blank = np.zeros_like(tiles[0])
    tiles += [blank] * (rows * cols - len(tiles))
    grid = [np.concatenate(tiles[r * cols:(r + 1) * cols], axis=1) for r in range(rows)]
    return np.concatenate(grid, axis=0)

"""Masks made elsewhere (SAM-2 run on a GPU, a hand-painted correction, another tool): `--import-masks DIR`.

One mask per frame, found by the frame's name (``frame_00012.png``), or by the name the frame had in
the folder it was extracted from (``frames.json``), with any common image extension. Plant or cube is
above half the mask's range: 255 of 0/255 masks (JPEG's ringing around the outline is left out), 1 of
0/1 masks (an image with an alpha channel, such as an RGBA frame, gives its alpha). Every frame needs one, of the
frame's size; what is wrong is said in one line.

Usage:
    masks = import_masks(Path("sam2_masks"), Workspace("ws/plant01"), names)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json
from plantsplat.workspace import Workspace

SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
MASK_THRESHOLD = 127
"""A mask of 0..255 holds the plant above this (0/1 masks: above 0)."""
SHOWN_MISSING = 5
"""The error for missing masks names this many frames."""


def _candidates(ws: Workspace, names: list[str]) -> dict[str, list[str]]:
    """Stems a mask of each frame may carry: the frame's own, and its source image's from ``frames.json``."""
    out = {n: [Path(n).stem] for n in names}
    if ws.frames_json.is_file():
        for f in read_json(ws.frames_json).get("frames", []):
            if f.get("name") in out and f.get("source_name"):
                out[f["name"]].append(Path(f["source_name"]).stem)
    return out


def import_masks(folder: Path, ws: Workspace, names: list[str]) -> dict[str, np.ndarray]:
    """``{frame name: bool mask [H, W]}`` from ``folder`` (see the module docstring)."""
    if not folder.is_dir():
        raise PlantsplatError(f"{folder}: not a folder; pass --import-masks a folder of mask images")
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in SUFFIXES}
    if not files:
        raise PlantsplatError(f"{folder}: no mask images ({', '.join(SUFFIXES)}); pass the folder that holds them")
    cands = _candidates(ws, names)
    missing = [n for n in names if not any(s in files for s in cands[n])]
    if missing:
        more = len(missing) - SHOWN_MISSING
        shown = ", ".join(missing[:SHOWN_MISSING]) + (f" and {more} more" if more > 0 else "")
        raise PlantsplatError(f"{folder}: no mask for {len(missing)} of {len(names)} frames ({shown}); name each mask "
                              "like its frame (e.g. frame_00000.png)")
    out = {}
    for n in names:
        path = files[next(s for s in cands[n] if s in files)]
        m = read_image(path, mode="rgba")[..., 3] if _has_alpha(path) else read_image(path, mode="gray")
        shape = read_image(ws.images_dir / n, mode="gray").shape
        if m.shape != shape:
            raise PlantsplatError(f"{path}: {m.shape[1]}x{m.shape[0]}, but frame {n} is {shape[1]}x{shape[0]}; "
                                  "masks must have their frame's size")
        out[n] = m > (0 if m.max() <= 1 else MASK_THRESHOLD)
    return out


def _has_alpha(path: Path) -> bool:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return img is not None and img.ndim == 3 and img.shape[2] == 4

"""Import the ROMI virtual scanner's test capture (RGBA views + COLMAP text poses) as a workspace.

The ROMI virtual plant (``../shared/datasets/romi_virtual_plant_synthetic``) is a rendered plant
with exact cameras and per-organ masks. Its RGBA images are in fact fully opaque (alpha 255, black
background) and its ``colmap_text`` poses do not match the per-image metadata (all optical axes
parallel), so the cameras come from ``metadata/images/*_rgb.json`` (world->camera, OpenCV axes) and
the mask from ``*_background.png`` (plant = below 128). The result is a workspace with
``images/``, ``masks/``, ``rgba/`` and a nerfstudio ``transforms.json`` (no SfM points).

Usage:
    ws = workspace_from_romi("../shared/datasets/romi_virtual_plant_synthetic", "ws/romi", size=224)
    len(ws.image_names())
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json, write_image_atomic, write_json_atomic
from plantsplat.workspace import IMAGE_PATTERN, Workspace


def workspace_from_romi(src: str | os.PathLike, dst: str | os.PathLike, size: int | None = None,
                        background: tuple[int, int, int] = (0, 0, 0)) -> Workspace:
    """Build a workspace from a ROMI virtual-plant folder; ``size`` = output side in px (None = 896)."""
    src, ws = Path(src), Workspace(dst)
    metas = sorted((src / "metadata" / "images").glob("*_rgb.json"))
    if not metas:
        raise PlantsplatError(f"{src / 'metadata' / 'images'}: no *_rgb.json cameras; not a ROMI virtual-plant folder")
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL (nerfstudio)
    frames = []
    bgc = np.array(background, np.float32)
    for i, meta in enumerate(metas):
        stem = meta.name[: -len("_rgb.json")]
        cam = read_json(meta)["camera"]
        W, H = cam["camera_model"]["width"], cam["camera_model"]["height"]
        fx, fy, cx, cy = cam["camera_model"]["params"][:4]
        w2c = np.eye(4)
        w2c[:3, :3] = np.asarray(cam["rotmat"], np.float64)
        w2c[:3, 3] = np.asarray(cam["tvec"], np.float64)
        s = (size or W) / W
        w, h = round(W * s), round(H * s)
        rgb = read_image(src / "images" / f"{stem}_rgb.png", "rgb")
        bgmask = read_image(src / "images" / f"{stem}_background.png", "gray")
        a = (bgmask < 128).astype(np.float32)  # [H, W] 1 = plant
        if (w, h) != (W, H):
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            a = cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)
        a = a[..., None]
        out = (rgb.astype(np.float32) * a + bgc * (1 - a)).round().astype(np.uint8)
        name = IMAGE_PATTERN.format(i)
        write_image_atomic(ws.images_dir / name, out)
        write_image_atomic(ws.masks_dir / name, (a[..., 0] * 255).round().astype(np.uint8))
        write_image_atomic(ws.rgba_dir / name, np.concatenate([out, (a * 255).round().astype(np.uint8)], -1))
        frames.append({
            "file_path": f"images/{name}", "fl_x": fx * s, "fl_y": fy * s, "cx": cx * s, "cy": cy * s, "w": w, "h": h,
            "transform_matrix": (np.linalg.inv(w2c) @ flip).tolist(),
        })
    write_json_atomic(ws.transforms_json, {"camera_model": "OPENCV", "frames": frames})
    return ws

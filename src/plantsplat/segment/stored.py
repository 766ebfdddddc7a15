"""What the segment stage keeps of the object it found, and cutting other images of the capture with it.

``WS/.plantsplat/segment/object.npz`` holds the plant flags and the geometry of the 3D object
(:class:`plantsplat.segment.object3d.ObjectModel`); ``WS/.plantsplat/segment/scene/`` the quick model
it was found in. :func:`segment_images` uses them to cut renders of the capture's cameras (the PBR
baseline of the training evaluation) exactly as the frames were cut.

Example:
    >>> from plantsplat.workspace import Workspace
    >>> scene_dir(Workspace("ws/plant_01"))
    PosixPath('ws/plant_01/.plantsplat/segment/scene')
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError
from plantsplat.io import atomic_path, read_json
from plantsplat.segment.config import SegmentConfig
from plantsplat.segment.frame import object_mask, object_prior, unresolved_px
from plantsplat.segment.object3d import ObjectModel
from plantsplat.train.checkpoint import load_model
from plantsplat.train.data import load_scene
from plantsplat.workspace import Workspace

OBJECT_FILE = ".plantsplat/segment/object.npz"
SCENE_DIR = ".plantsplat/segment/scene"


def scene_dir(ws: Workspace) -> Path:
    """Folder of the quick whole-scene model (:mod:`plantsplat.segment.scene`)."""
    return ws.root / SCENE_DIR


def scene_resolution(ws: Workspace) -> int:
    """Longest side (px) of the frames the quick model was trained on, as its run recorded it."""
    path = scene_dir(ws) / "config.json"
    recorded = read_json(path).get("resolved", {}).get("max_resolution") if path.is_file() else None
    return int(recorded) if recorded else SegmentConfig().scene_resolution


def save_object(ws: Workspace, obj) -> None:
    """The plant flags and geometry of the 3D object, beside the quick model (segmenting renders reuses them)."""
    path = ws.root / OBJECT_FILE
    with atomic_path(path, suffix=".npz") as tmp:
        parts = {} if obj.part is None else {"part": obj.part}
        np.savez(tmp, plant=obj.plant, axis=obj.axis, up=obj.up, info=json.dumps(obj.info), **parts,
                 cube=json.dumps(None if obj.cube is None else obj.cube.record()))


def load_object(ws: Workspace):
    """The 3D object the segment stage found (:func:`save_object`) with its quick model, and the cameras by name."""
    path = ws.root / OBJECT_FILE
    if not path.is_file():
        raise PlantsplatError(f"{path}: missing; run `plantsplat segment {ws.root}` (the 3d backend) first")
    data = np.load(path)
    params, _ = load_model(ws, scene_dir(ws))
    cube = json.loads(str(data["cube"]))
    obj = ObjectModel(params={k: v.detach().cpu() for k, v in params.items()}, plant=data["plant"],
                      cube=None if cube is None else CubeSpec.from_record(cube),
                      axis=data["axis"], up=data["up"], info=json.loads(str(data["info"])),
                      part=data["part"] if "part" in data.files else None)
    return obj, {v.name: v for v in load_scene(ws, need_masks=False, load_images=False).views}


def segment_images(ws: Workspace, images: dict[str, np.ndarray], band_px: int | None = None) -> dict[str, np.ndarray]:
    """Masks ``{name: [h, w] bool}`` of images taken through the workspace's pinhole cameras (such as renders of its
    test views, ``[h, w, 3]`` uint8 at any size), cut as the segment stage cuts the frames: the 3D object it
    found, drawn into each camera and refined on the image."""
    obj, views = load_object(ws)
    band = SegmentConfig().refine_band_px if band_px is None else band_px
    resolution = scene_resolution(ws)
    out = {}
    for name, rgb in images.items():
        plant, cube = object_prior(obj, views[name])
        if plant.shape != rgb.shape[:2]:
            plant, cube = (cv2.resize(p, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_AREA) for p in (plant, cube))
        out[name] = object_mask(rgb, plant, cube, band, unresolved_px(rgb.shape, resolution))
    return out

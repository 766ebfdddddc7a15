"""A user's own camera model (COLMAP or nerfstudio) put onto the workspace's frames.

Images are matched by name, or through ``frames.json`` by the name they had in the folder the frames
came from (a model made on the original photos imports onto the extracted frames).

Usage:
    rec = rename_images(read_colmap(Path("my_model/sparse/0")), {"IMG_0001.jpg": "frame_00000.png"})
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_json
from plantsplat.workspace import Workspace


def name_map(ws: Workspace, model_names: list[str], names: list[str]) -> dict[str, str]:
    """Map an imported model's image names onto workspace image names (same name, or frames.json source name)."""
    have = set(names)
    direct = {n: n for n in model_names if n in have}
    if len(direct) == len(model_names) or not ws.frames_json.is_file():
        return direct
    try:
        frames = read_json(ws.frames_json).get("frames", [])
    except PlantsplatError:
        return direct
    by_source = {Path(f["source_name"]).name: f["name"] for f in frames if f.get("source_name")}
    out = dict(direct)
    for n in model_names:
        if n not in out and Path(n).name in by_source and by_source[Path(n).name] in have:
            out[n] = by_source[Path(n).name]
    return out


def rename_images(rec, mapping: dict[str, str]):
    """A copy of ``rec`` keeping only the posed images in ``mapping``, renamed to workspace names (no points)."""
    cam_ids = {im.camera_id for im in rec.images.values() if im.has_pose and im.name in mapping}
    if len(cam_ids) != 1:
        raise PlantsplatError(
            f"the imported model uses {len(cam_ids)} cameras for the workspace frames; plantsplat expects one shared camera"
        )
    cam = rec.cameras[next(iter(cam_ids))]
    out = pycolmap.Reconstruction()
    new_cam = pycolmap.Camera.create_from_model_name(1, cam.model.name, cam.focal_length_x, cam.width, cam.height)
    new_cam.params = cam.params
    out.add_camera_with_trivial_rig(new_cam)
    posed = [im for im in rec.images.values() if im.has_pose and im.name in mapping]
    for k, im in enumerate(sorted(posed, key=lambda i: mapping[i.name])):
        new = pycolmap.Image(name=mapping[im.name], keypoints=np.zeros((0, 2)), camera_id=1, image_id=k + 1)
        out.add_image_with_trivial_frame(new, im.cam_from_world())
    return out

"""COLMAP and nerfstudio interoperability: read, write and import camera models.

- COLMAP models (binary or text folders with cameras/images/points3D) are read and written by
  pycolmap; outputs are written to a temporary folder and swapped in, so a crash never leaves a
  half-written model.
- nerfstudio ``transforms.json``: shared intrinsics (``camera_model`` "OPENCV" or "PINHOLE",
  ``fl_x fl_y cx cy w h k1 k2 p1 p2``) and per-frame ``transform_matrix`` = camera-to-world in
  OpenGL axes (x right, y up, z backward). COLMAP uses OpenCV axes (y down, z forward): the two
  differ by ``diag(1, -1, -1)`` on the camera side.

Usage:
    rec = read_colmap("my_model/sparse/0")
    write_transforms(rec, "ws/transforms.json", mask_prefix="masks")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_json, staged_dir, write_json_atomic
from plantsplat.ply import write_point_cloud

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])

# COLMAP camera model -> names of its parameters (in order)
_PARAMS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


def camera_intrinsics(camera) -> dict:
    """nerfstudio-style intrinsics of a pycolmap camera (``fl_x fl_y cx cy w h k1 k2 p1 p2``)."""
    name = camera.model.name
    if name not in _PARAMS:
        raise PlantsplatError(
            f"camera model {name} is not supported for transforms.json; use one of {', '.join(_PARAMS)}"
        )
    v = dict(zip(_PARAMS[name], (float(x) for x in camera.params)))
    fx = v.get("fx", v.get("f"))
    fy = v.get("fy", v.get("f"))
    return {
        "camera_model": "OPENCV",
        "fl_x": fx,
        "fl_y": fy,
        "cx": v["cx"],
        "cy": v["cy"],
        "w": int(camera.width),
        "h": int(camera.height),
        "k1": v.get("k1", 0.0),
        "k2": v.get("k2", 0.0),
        "p1": v.get("p1", 0.0),
        "p2": v.get("p2", 0.0),
    }


def c2w_opencv(image) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) of a registered pycolmap image."""
    M = np.eye(4)
    M[:3, :] = np.asarray(image.cam_from_world().inverse().matrix())
    return M


def registered_images(rec) -> dict:
    """The frames of model ``rec`` that have a camera, by name (in name order)."""
    return {im.name: im for im in sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)}


def write_colmap(rec, out_dir: Path, text: bool = False) -> None:
    """Write a COLMAP model (binary, or text with ``text=True``) to ``out_dir`` atomically."""
    with staged_dir(out_dir) as tmp:
        if text:
            rec.write_text(str(tmp))
        else:
            rec.write_binary(str(tmp))


def read_colmap(path: Path):
    """Read a COLMAP model folder (binary or text); a broken or missing model is a one-line error.

    ``path`` may be the model folder itself (``sparse/0``) or a parent holding ``0/`` or ``sparse/0``.
    """
    path = Path(path)
    if not path.exists():
        raise PlantsplatError(f"{path}: COLMAP model not found; pass the folder holding cameras/images/points3D")
    cands = [path, path / "0", path / "sparse" / "0", path / "sparse"]
    model = next(
        (c for c in cands if (c / "cameras.bin").is_file() or (c / "cameras.txt").is_file()), None
    )
    if model is None:
        raise PlantsplatError(
            f"{path}: no cameras.bin or cameras.txt found; pass a COLMAP model folder (e.g. sparse/0)"
        )
    for stem in ("cameras", "images"):
        if not ((model / f"{stem}.bin").is_file() or (model / f"{stem}.txt").is_file()):
            raise PlantsplatError(f"{model}: {stem}.bin/.txt missing; the COLMAP model is incomplete")
    try:
        if (model / "cameras.bin").is_file():
            if not (model / "points3D.bin").is_file():
                raise PlantsplatError(f"{model}: points3D.bin missing; the COLMAP model is incomplete")
            rec = pycolmap.Reconstruction()
            rec.read_binary(str(model))
        else:
            if not (model / "points3D.txt").is_file():
                raise PlantsplatError(f"{model}: points3D.txt missing (it may be empty but must exist)")
            rec = pycolmap.Reconstruction()
            rec.read_text(str(model))
    except PlantsplatError:
        raise
    except Exception as exc:
        msg = str(exc).strip().splitlines()[-1][:200] if str(exc).strip() else type(exc).__name__
        raise PlantsplatError(f"{model}: unreadable COLMAP model ({msg}); re-export it from COLMAP") from exc
    if rec.num_reg_images() == 0:
        raise PlantsplatError(f"{model}: the COLMAP model has no registered images")
    return rec


def write_transforms(
    rec,
    path: Path,
    image_prefix: str = "images",
    mask_prefix: str | None = None,
    extra: dict | None = None,
) -> dict:
    """Write a nerfstudio ``transforms.json`` for the registered images of ``rec`` (single camera).

    Frames get ``file_path`` ``images/<name>`` and, with ``mask_prefix``, ``mask_path``
    ``<mask_prefix>/<name>`` (where the segment stage writes the masks; nerfstudio reads them from
    there). ``extra`` keys (e.g. ``applied_transform``, ``scale``) are added at the top level.
    Returns the written dict.
    """
    images = list(registered_images(rec).values())
    cam_ids = {im.camera_id for im in images}
    if len(cam_ids) != 1:
        raise PlantsplatError(f"{path}: the model has {len(cam_ids)} cameras; plantsplat expects one shared camera")
    data = camera_intrinsics(rec.cameras[cam_ids.pop()])
    frames = []
    for im in images:
        f = {
            "file_path": f"{image_prefix}/{im.name}",
            "transform_matrix": (c2w_opencv(im) @ OPENCV_TO_OPENGL).tolist(),
            "colmap_im_id": int(im.image_id),
        }
        if mask_prefix is not None:
            f["mask_path"] = f"{mask_prefix}/{im.name}"
        frames.append(f)
    data["frames"] = frames
    if extra:
        data.update(extra)
    write_json_atomic(path, data)
    return data


def read_transforms(path: Path, image_names: list[str] | None = None):
    """Build a pycolmap Reconstruction (cameras and poses, no points) from a nerfstudio ``transforms.json``.

    Frames are matched to ``image_names`` (the workspace images) by file name; with ``image_names``
    None every frame is kept. Per-frame intrinsics are not supported (one shared camera).
    """
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise PlantsplatError(f"{path}: no 'frames' list; not a nerfstudio transforms.json")
    try:
        fx, fy = float(data["fl_x"]), float(data.get("fl_y", data["fl_x"]))
        w, h = int(data["w"]), int(data["h"])
        cx, cy = float(data.get("cx", w / 2)), float(data.get("cy", h / 2))
    except (KeyError, TypeError, ValueError) as exc:
        raise PlantsplatError(
            f"{path}: missing or invalid shared intrinsics ({exc}); need fl_x, fl_y, cx, cy, w, h at the top level"
        ) from exc
    model = str(data.get("camera_model", "OPENCV")).upper()
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise PlantsplatError(f"{path}: camera_model {model} is not supported (use OPENCV or PINHOLE)")
    dist = [float(data.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")]
    if any(dist):
        cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", fx, w, h)
        cam.params = [fx, fy, cx, cy, *dist]
    else:
        cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", fx, w, h)
        cam.params = [fx, fy, cx, cy]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    wanted = set(image_names) if image_names is not None else None
    next_id = 1
    for i, fr in enumerate(data["frames"]):
        try:
            name = Path(str(fr["file_path"])).name
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise PlantsplatError(f"{path}: frame {i} has no valid file_path/transform_matrix") from exc
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise PlantsplatError(f"{path}: frame {i} ({name}): transform_matrix is not a finite 4x4 matrix")
        if any(k in fr for k in ("fl_x", "fl_y")):
            raise PlantsplatError(f"{path}: per-frame intrinsics are not supported; use one shared camera")
        if wanted is not None and name not in wanted:
            continue
        c2w = M @ OPENCV_TO_OPENGL  # OpenGL -> OpenCV camera axes
        Rw = c2w[:3, :3]
        U, _, Vt = np.linalg.svd(Rw)
        Rw = U @ Vt  # re-orthonormalise (scale-free rotation)
        w2c = np.eye(4)
        w2c[:3, :3] = Rw.T
        w2c[:3, 3] = -Rw.T @ c2w[:3, 3]
        im = pycolmap.Image(name=name, camera_id=1, image_id=next_id)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(w2c[:3, :]))
        next_id += 1
    if rec.num_reg_images() == 0:
        raise PlantsplatError(f"{path}: none of its frames name an image in the workspace's images/")
    return rec


def write_points_ply(rec, path: Path) -> int:
    """Write the model's 3D points as a binary PLY (x, y, z float, red, green, blue uchar); returns the count."""
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts]).reshape(-1, 3)  # [N, 3]
    rgb = np.array([p.color for p in pts]).reshape(-1, 3)  # [N, 3]
    write_point_cloud(path, xyz, rgb)
    return len(pts)

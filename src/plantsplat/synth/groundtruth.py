"""Ground truth of a synthetic capture: dense surface samples, PLY files, traits and marker visibility.

``plant_gt.ply`` holds every vertex of the plant's meshes plus area-uniform random samples on its
triangles (``density`` per cm^2), so that extremes (height, widths) and convex hulls equal those of the
rendered geometry. ``scene_gt.ply`` adds the cube's five visible faces (organ 10, instance = face index
in ``plantsplat.cube.FACE_NAMES`` order) with the colours of their marker texture.

Example:
    >>> import numpy as np
    >>> from plantsplat.synth.mesh import box_mesh
    >>> s = sample_surface([box_mesh((0, 0, 0), (1, 1, 1), cls=1)], np.zeros((1, 8, 8, 3), np.uint8), 50.0,
    ...                    np.random.default_rng(0))
    >>> s["xyz"].shape[1], float(s["xyz"][:, 2].max())
    (3, 1.0)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from plantsplat.cube import FACE_NAMES
from plantsplat.ply import write_point_cloud
from plantsplat.synth.mesh import CUBE_BASE, ORGAN_OF_CLASS, Mesh
from plantsplat.traitdefs import geometric_traits

CUBE_ORGAN = 10

def _texture_colour(layers: np.ndarray, layer: int, uv: np.ndarray, tint: np.ndarray) -> np.ndarray:
    size = layers.shape[1]
    u = (np.floor(uv[:, 0] * size).astype(np.int64)) % size
    v = (np.floor(uv[:, 1] * size).astype(np.int64)) % size
    tex = layers[layer][v, u].astype(np.float64)  # [N, 3]
    return np.clip(tex * tint, 0, 255).astype(np.uint8)


def sample_surface(meshes: list[Mesh], layers: np.ndarray, density: float, rng: np.random.Generator,
                   organ_of=None) -> dict[str, np.ndarray]:
    """Vertices plus ``density`` random points per cm^2 on the meshes' triangles.

    Returns ``xyz [N, 3]``, ``rgb [N, 3]`` uint8 (albedo: texture x vertex colour), ``organ [N]``,
    ``instance [N]``. ``organ_of(mesh)`` gives the organ code (default: the plant organ of the class).
    """
    organ_of = organ_of or (lambda m: ORGAN_OF_CLASS[m.cls])
    xyz, rgb, organ, inst = [], [], [], []
    for m in meshes:
        area = m.area()
        n = int(rng.poisson(density * area.sum()))
        tri = rng.choice(len(area), size=n, p=area / area.sum()) if n else np.zeros(0, int)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        bary = np.stack([1 - s, s * (1 - r2), s * r2], 1)  # [n, 3] uniform on a triangle
        idx = m.f[tri]  # [n, 3]
        p = np.einsum("nk,nkd->nd", bary, m.v[idx])
        uv = np.einsum("nk,nkd->nd", bary, m.uv[idx])
        col = np.einsum("nk,nkd->nd", bary, m.col[idx])
        p = np.concatenate([m.v, p])
        uv = np.concatenate([m.uv, uv])
        col = np.concatenate([m.col, col])
        xyz.append(p)
        rgb.append(_texture_colour(layers, m.layer, uv, col))
        organ.append(np.full(len(p), organ_of(m), np.uint8))
        inst.append(np.full(len(p), m.instance, np.int32))
    return dict(xyz=np.concatenate(xyz), rgb=np.concatenate(rgb), organ=np.concatenate(organ),
                instance=np.concatenate(inst))


def cube_samples(cube_meshes: list[Mesh], layers: np.ndarray, density: float, rng: np.random.Generator) -> dict:
    """Samples on the cube's faces except the bottom one (it stands on the platform and is never seen)."""
    faces = [m for m in cube_meshes if m.cls != CUBE_BASE + 5]
    return sample_surface(faces, layers, density, rng, organ_of=lambda m: CUBE_ORGAN)


def write_ply(path: str | Path, s: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY with x, y, z (float32), red, green, blue, organ (uchar), instance (int32)."""
    write_point_cloud(path, s["xyz"], s["rgb"], organ=np.asarray(s["organ"], np.uint8),
                      instance=np.asarray(s["instance"], np.int32))


def traits(xyz: np.ndarray, n_fruits: int, soil_z: float) -> dict[str, float]:
    """Ground-truth traits with the shared definitions of :mod:`plantsplat.traitdefs`: height above the soil at
    ``soil_z`` (``n_fruits``: the ripe, red fruits, which is what ``fruit_count`` counts)."""
    t = geometric_traits(xyz, soil_z=soil_z)
    t["fruit_count"] = int(n_fruits)
    return t


def markers_visible(ids: np.ndarray, c2w: np.ndarray, K: np.ndarray, markers: dict[str, np.ndarray],
                    cube, T_world_cube: np.ndarray, min_cos: float = 0.3, min_side_px: float = 14.0,
                    min_unoccluded: float = 0.98, margin_px: float = 3.0) -> list[int]:
    """Marker ids whose face looks at the camera and whose square is in the image and unoccluded.

    A marker counts as visible when its face normal makes less than ``acos(min_cos)`` with the
    direction to the camera, its projected square lies ``margin_px`` inside the image, its shortest
    projected side is at least ``min_side_px`` and at least ``min_unoccluded`` of the pixels inside
    the square show that face in the id pass.
    """
    H, W = ids.shape
    w2c = np.linalg.inv(c2w)
    eye = c2w[:3, 3]
    out = []
    for i, face in enumerate(FACE_NAMES):
        mid = cube.face_ids[i]
        X = np.asarray(markers[str(mid)])  # [4, 3] world
        c, n, _, _ = cube.face_frame(face)
        nw = T_world_cube[:3, :3] @ n
        cw = T_world_cube[:3, :3] @ c + T_world_cube[:3, 3]
        to_cam = eye - cw
        if np.dot(nw, to_cam) / np.linalg.norm(to_cam) < min_cos:
            continue
        Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
        if np.any(Xc[:, 2] <= 1.0):
            continue
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
        if np.any(uv < margin_px) or np.any(uv[:, 0] > W - 1 - margin_px) or np.any(uv[:, 1] > H - 1 - margin_px):
            continue
        sides = np.linalg.norm(uv - np.roll(uv, -1, axis=0), axis=1)
        if sides.min() < min_side_px:
            continue
        poly = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(poly, np.round(uv * 16).astype(np.int32), 1, cv2.LINE_8, shift=4)
        inside = poly.astype(bool)
        if inside.sum() == 0:
            continue
        if np.mean(ids[inside] == CUBE_BASE + i) >= min_unoccluded:
            out.append(int(mid))
    return out


def project_to_pixels(K: np.ndarray, c2w: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``[N, 2]`` (OpenCV convention) of world points ``X [N, 3]``."""
    w2c = np.linalg.inv(c2w)
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    uv = Xc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def true_transforms(ground_truth: dict, frames: list[tuple[str, int]]) -> dict:
    """The capture's true cameras as a nerfstudio ``transforms.json`` dict.

    ``frames`` pairs an image name (written as ``images/<name>``) with the video frame index it shows.
    Poses become OpenGL camera axes; the principal point moves by +0.5 px, from synth's convention
    (pixel centres at integer coordinates) to nerfstudio's and COLMAP's.

    Example:
        >>> gt = {"intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 269.5, "cy": 479.5, "width": 540, "height": 960},
        ...       "frames": [{"c2w": np.eye(4).tolist()}]}
        >>> t = true_transforms(gt, [("frame_00000.png", 0)])
        >>> t["cx"], t["frames"][0]["transform_matrix"][1][1]
        (270.0, -1.0)
    """
    intr = ground_truth["intrinsics"]
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV -> OpenGL camera axes
    return {
        "camera_model": "PINHOLE",
        "fl_x": intr["fx"], "fl_y": intr["fy"], "cx": intr["cx"] + 0.5, "cy": intr["cy"] + 0.5,
        "w": intr["width"], "h": intr["height"],
        "frames": [
            {"file_path": f"images/{name}",
             "transform_matrix": (np.asarray(ground_truth["frames"][index]["c2w"], dtype=np.float64) @ flip).tolist()}
            for name, index in frames
        ],
    }

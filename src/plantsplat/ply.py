"""PLY files: the one reader and writer of every PLY plantsplat reads or writes (a ``vertex`` element).

Three layouts, all binary little-endian and written atomically:

- a point cloud (:func:`write_point_cloud`, :func:`read_point_cloud`): ``x y z`` float32, ``red green
  blue`` uchar, then any extra columns (``opacity``, ``scale_0..2``, ``organ``...). Any PLY with x, y,
  z vertices reads as one; float colours in [0, 1] are scaled to 0..255;
- a 3D Gaussian Splatting model in the Inria layout (:func:`write_splat`, :func:`read_splat`):
  ``x y z nx ny nz f_dc_0..2 f_rest_0..M opacity scale_0..2 rot_0..3`` as float32, opacity as a
  logit, scales as logs, rotations (w, x, y, z), ``f_rest`` channel-major
  (``f_rest_{c * (K-1) + k}``), as the Inria code and the usual splat viewers read it;
- any table of columns (:func:`write_vertices`, :func:`read_vertices`).

Example:
    >>> import numpy as np, tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "pts.ply")
    >>> write_point_cloud(path, np.zeros((2, 3)), np.full((2, 3), 200, np.uint8), opacity=np.ones(2))
    >>> cloud = read_point_cloud(path)
    >>> cloud["xyz"].shape, cloud["rgb"][0].tolist(), cloud["opacity"].tolist(), cloud["scales"]
    ((2, 3), [200, 200, 200], [1.0, 1.0], None)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement
from scipy.spatial.transform import Rotation

from plantsplat.errors import PlantsplatError
from plantsplat.io import atomic_path

SPLAT_COLUMNS = {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                 "rot_0", "rot_1", "rot_2", "rot_3"}


def write_vertices(path: str | os.PathLike, columns: dict[str, np.ndarray]) -> None:
    """Write columns of equal length (each keeps its dtype) as a binary PLY's vertex element, atomically."""
    n = len(next(iter(columns.values()))) if columns else 0
    arrays = {k: np.asarray(v) for k, v in columns.items()}
    rec = np.empty(n, dtype=[(k, a.dtype.str) for k, a in arrays.items()])
    for k, a in arrays.items():
        rec[k] = a
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(tmp))


def read_vertices(path: str | os.PathLike, hint: str = "re-run the stage that wrote it") -> np.ndarray:
    """The vertex element of a PLY as a structured array; a missing or unreadable file is a one-line error
    that ends with ``hint``."""
    path = Path(path)
    if not path.is_file():
        raise PlantsplatError(f"{path}: not found; {hint}")
    try:
        return PlyData.read(str(path))["vertex"].data
    except Exception as exc:  # plyfile raises many types on a damaged file
        raise PlantsplatError(f"{path}: not a readable PLY with vertices ({type(exc).__name__}); {hint}") from exc


def write_point_cloud(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray, **extra: np.ndarray) -> None:
    """``x y z`` (float32), ``red green blue`` (uchar, from uint8 ``rgb`` [N, 3]) and ``extra`` columns
    (float arrays as float32, ``[N, 3]`` arrays as ``name_0..2``; integer arrays keep their type)."""
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    for name, a in extra.items():
        a = np.asarray(a)
        a = a.astype(np.float32) if a.dtype.kind == "f" else a
        if a.ndim == 2:
            cols.update({f"{name}_{i}": a[:, i] for i in range(a.shape[1])})
        else:
            cols[name] = a
    write_vertices(path, cols)


def read_point_cloud(path: str | os.PathLike, hint: str = "re-run the stage that wrote it") -> dict:
    """``{'xyz' [N, 3] float64, 'rgb' [N, 3] uint8 | None, 'opacity' [N] | None, 'scales' [N, 3] | None}``
    of any PLY with x, y, z vertices, plus every other column under its own name."""
    v = read_vertices(path, hint)
    names = set(v.dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise PlantsplatError(f"{path}: the PLY's vertices have no x, y, z; give a point cloud")
    out = {"xyz": np.stack([np.asarray(v[k], np.float64) for k in "xyz"], axis=1), "rgb": None, "opacity": None,
           "scales": None}
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(v[k]) for k in ("red", "green", "blue")], axis=1)
        if rgb.dtype.kind == "f" and rgb.size and np.nanmax(rgb) <= 1.0:  # colours stored as floats in [0, 1]
            rgb = rgb * 255.0
        out["rgb"] = np.clip(np.round(rgb), 0, 255).astype(np.uint8) if rgb.dtype.kind == "f" else \
            np.clip(rgb, 0, 255).astype(np.uint8)
    if "opacity" in names:
        out["opacity"] = np.asarray(v["opacity"], np.float64)
    if {"scale_0", "scale_1", "scale_2"} <= names:
        out["scales"] = np.stack([np.asarray(v[f"scale_{i}"], np.float64) for i in range(3)], axis=1)
    known = {"x", "y", "z", "red", "green", "blue", "opacity", "scale_0", "scale_1", "scale_2"}
    out.update({k: np.asarray(v[k]) for k in v.dtype.names or () if k not in known})
    return out


def write_splat(path: str | os.PathLike, means: np.ndarray, scales_log: np.ndarray, quats: np.ndarray,
                opacity_logit: np.ndarray, sh0: np.ndarray, shN: np.ndarray) -> None:
    """Gaussians in the Inria layout: ``means`` [N, 3], ``scales_log`` [N, 3], ``quats`` [N, 4] (wxyz),
    ``opacity_logit`` [N], ``sh0`` [N, 1, 3], ``shN`` [N, K-1, 3]."""
    n = len(means)
    f32 = np.float32
    f_dc = np.asarray(sh0, f32).reshape(n, 3)
    f_rest = np.asarray(shN, f32).reshape(n, -1, 3).transpose(0, 2, 1).reshape(n, -1)  # channel-major
    means, scales_log, quats = (np.asarray(a, f32) for a in (means, scales_log, quats))
    cols = {**{k: means[:, i] for i, k in enumerate("xyz")}, **{k: np.zeros(n, f32) for k in ("nx", "ny", "nz")},
            **{f"f_dc_{i}": f_dc[:, i] for i in range(3)}, **{f"f_rest_{i}": f_rest[:, i] for i in range(f_rest.shape[1])},
            "opacity": np.asarray(opacity_logit, f32).reshape(n), **{f"scale_{i}": scales_log[:, i] for i in range(3)},
            **{f"rot_{i}": quats[:, i] for i in range(4)}}
    write_vertices(path, cols)


def read_splat(path: str | os.PathLike, hint: str = "export it with `plantsplat export`") -> dict[str, np.ndarray]:
    """An Inria-layout 3DGS PLY as raw (not activated) float32 arrays: ``means`` [N, 3], ``scales`` [N, 3]
    (log), ``quats`` [N, 4] (wxyz), ``opacities`` [N] (logit), ``sh0`` [N, 1, 3], ``shN`` [N, K-1, 3]."""
    v = read_vertices(path, hint)
    names = set(v.dtype.names or ())
    missing = sorted(SPLAT_COLUMNS - names)
    if missing:
        raise PlantsplatError(f"{path}: not a 3D Gaussian Splatting PLY (no {', '.join(missing[:4])}); {hint}")

    def col(c):
        return np.asarray(v[c], np.float32)

    n = len(v)
    rest = sorted((c for c in names if c.startswith("f_rest_")), key=lambda c: int(c.split("_")[-1]))
    if len(rest) % 3:
        raise PlantsplatError(f"{path}: {len(rest)} f_rest properties, not a multiple of 3; {hint}")
    f_rest = np.stack([col(c) for c in rest], -1) if rest else np.zeros((n, 0), np.float32)
    return {
        "means": np.stack([col(k) for k in "xyz"], -1),
        "scales": np.stack([col(f"scale_{i}") for i in range(3)], -1),
        "quats": np.stack([col(f"rot_{i}") for i in range(4)], -1),
        "opacities": col("opacity"),
        "sh0": np.stack([col(f"f_dc_{i}") for i in range(3)], -1)[:, None, :],
        "shN": f_rest.reshape(n, 3, len(rest) // 3).transpose(0, 2, 1),  # n = 0 too
    }


def write_splat_rows(path: str | os.PathLike, source: str | os.PathLike, rows: np.ndarray) -> None:
    """The rows ``rows`` of the splat PLY ``source``, every column as it is there, as a PLY of their own (atomically)."""
    v = read_vertices(source, "export it with `plantsplat export`")[np.asarray(rows, np.int64)]
    write_vertices(path, {name: v[name] for name in v.dtype.names})


def is_splat(path: str | os.PathLike) -> bool:
    """Whether a PLY's header names the Inria 3DGS columns (read from the header only)."""
    with open(path, "rb") as f:
        head = f.read(16384)
    end = head.find(b"end_header")
    names = {ln.split()[-1].decode(errors="replace") for ln in head[: max(end, 0)].split(b"\n")
             if ln.startswith(b"property")}
    return SPLAT_COLUMNS <= names


def gaussian_extent_points(
    means: np.ndarray, scales: np.ndarray, quats: np.ndarray, k_sigma: float
) -> np.ndarray:
    """The centres and the 6 ends of each Gaussian's principal axes at ``k_sigma`` standard deviations.

    ``means [N, 3]``, ``scales [N, 3]`` (activated standard deviations), ``quats [N, 4]`` (w, x, y, z).
    Returns ``[7 N, 3]`` in 7 blocks of N: the centres, then each axis end of every Gaussian (so
    per-Gaussian attributes repeat with ``np.tile(attr, (7, 1))``).

    Example:
        >>> p = gaussian_extent_points(np.zeros((1, 3)), np.array([[1.0, 2, 3]]), np.array([[1.0, 0, 0, 0]]), 2.0)
        >>> float(p[:, 2].max()), float(p[:, 1].min())
        (6.0, -4.0)
    """
    q = np.asarray(quats, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # [N, 3, 3], columns = principal axes
    ax = R * (k_sigma * np.asarray(scales, dtype=np.float64))[:, None, :]  # [N, 3, 3] scaled columns
    means = np.asarray(means, np.float64)
    ends = [means + sgn * ax[:, :, j] for j in range(3) for sgn in (1.0, -1.0)]  # 6 x [N, 3]
    return np.concatenate([means, *ends])  # block k holds point k of every Gaussian


def read_splat_extent_cloud(path: str | Path, opacity_min: float, k_sigma: float) -> dict[str, np.ndarray]:
    """Point cloud of the opaque Gaussians of an Inria-layout ``splat.ply`` with their extents
    (see :func:`gaussian_extent_points`; ``k_sigma`` 0: the centres alone); colours from the SH DC term.
    The PLY's opacity is a logit: it is mapped through the sigmoid before ``opacity_min`` applies.
    ``rows``: the PLY row of each Gaussian kept (the order of the centres' block)."""
    g = read_splat(path)
    op = 1.0 / (1.0 + np.exp(-np.asarray(g["opacities"], np.float64)))  # [N]
    keep = op >= opacity_min
    means = np.asarray(g["means"], np.float64)[keep]
    scales = np.exp(np.asarray(g["scales"], np.float64)[keep])
    pts = gaussian_extent_points(means, scales, np.asarray(g["quats"])[keep], k_sigma) if k_sigma > 0 else means
    rgb = np.clip(0.5 + 0.28209479177387814 * np.asarray(g["sh0"], np.float64)[keep, 0, :], 0, 1)
    rgb = np.round(rgb * 255).astype(np.uint8)
    centre = np.zeros(len(pts), bool)
    centre[: len(means)] = True
    return {"xyz": pts, "rgb": np.tile(rgb, (len(pts) // max(len(means), 1), 1)), "opacity": None, "scales": None,
            "centre": centre,
            "gaussians": int(keep.sum()), "rows": np.flatnonzero(keep)}

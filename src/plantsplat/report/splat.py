"""Convert the exported Gaussian model and point cloud into the compact arrays the report's viewer reads.

The viewer (Spark, a three.js Gaussian-splat renderer) reads the ``.splat`` layout, 32 bytes per
Gaussian, little-endian::

    position  float32 x 3        (world units, here centimetres, z up)
    scale     float32 x 3        (linear standard deviations: exp of the PLY's log scales)
    colour    uint8   x 4        (RGB from the degree-0 SH coefficient, A = sigmoid(opacity logit))
    rotation  uint8   x 4        (unit quaternion w, x, y, z mapped from [-1, 1] to [0, 255])

That is 7.7x smaller than the Inria PLY with degree-3 SH (248 bytes per Gaussian); the view-dependent
SH terms are dropped, which is fine for looking at a plant.

Example:
    >>> import numpy as np
    >>> g = SplatArrays(means=np.zeros((1, 3), np.float32), log_scales=np.full((1, 3), -2.0, np.float32),
    ...                 quats=np.array([[1.0, 0, 0, 0]], np.float32), f_dc=np.zeros((1, 3), np.float32),
    ...                 opacity_logits=np.zeros(1, np.float32))
    >>> len(encode_splat(g))
    32
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.ply import read_point_cloud, read_vertices

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonic constant: colour = 0.5 + SH_C0 * f_dc."""

SPLAT_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))]
)
"""One record of the ``.splat`` layout (32 bytes)."""

_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


@dataclass
class SplatArrays:
    """Gaussian parameters as stored in an Inria-layout 3DGS PLY."""

    means: np.ndarray  # [N, 3] float32, world (cm)
    log_scales: np.ndarray  # [N, 3] float32, log of standard deviations
    quats: np.ndarray  # [N, 4] float32, w x y z (not necessarily normalised)
    f_dc: np.ndarray  # [N, 3] float32, degree-0 SH coefficients
    opacity_logits: np.ndarray  # [N] float32

    def __len__(self) -> int:
        return len(self.means)


def read_splat_ply(path: str | os.PathLike) -> SplatArrays:
    """Read an Inria-layout 3DGS PLY (x, y, z, f_dc_*, opacity, scale_*, rot_*).

    Usage:
        g = read_splat_ply("ws/export/splat.ply")
        g.means.shape
    """
    path = Path(path)
    v = read_vertices(path, "re-run `plantsplat export`")
    names = set(v.dtype.names or ())
    missing = [k for k in _REQUIRED if k not in names]
    if missing:
        raise PlantsplatError(
            f"{path}: not a 3D Gaussian Splatting PLY (missing {', '.join(missing[:4])}); "
            "re-run `plantsplat export`"
        )

    def cols(keys):
        return np.stack([np.asarray(v[k], dtype=np.float32) for k in keys], axis=1)

    g = SplatArrays(
        means=cols(["x", "y", "z"]),
        log_scales=cols(["scale_0", "scale_1", "scale_2"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        f_dc=cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        opacity_logits=np.asarray(v["opacity"], dtype=np.float32),
    )
    finite = np.isfinite(g.means).all(1) & np.isfinite(g.log_scales).all(1) & np.isfinite(g.quats).all(1)
    finite &= np.isfinite(g.f_dc).all(1) & np.isfinite(g.opacity_logits)
    if not finite.all():
        g = SplatArrays(g.means[finite], g.log_scales[finite], g.quats[finite], g.f_dc[finite], g.opacity_logits[finite])
    return g


def encode_splat(g: SplatArrays, max_gaussians: int | None = None) -> bytes:
    """Encode Gaussians in the ``.splat`` layout, most visible first (large and opaque).

    ``max_gaussians`` keeps only the most visible ones (by opacity x volume) when the model is larger.

    Usage:
        raw = encode_splat(g)
        np.frombuffer(raw, SPLAT_DTYPE)["position"].shape
    """
    n = len(g)
    opacity = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))  # [N]
    scales = np.exp(np.clip(g.log_scales.astype(np.float64), -30, 30))  # [N, 3]
    importance = opacity * np.exp(np.clip(g.log_scales.astype(np.float64).sum(1), -80, 80))  # [N]
    order = np.argsort(-importance, kind="stable")
    if max_gaussians is not None and n > max_gaussians:
        order = order[:max_gaussians]
    q = g.quats[order].astype(np.float64)  # [M, 4]
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(qn > 0, q / np.maximum(qn, 1e-12), np.array([1.0, 0, 0, 0]))
    rgb = 0.5 + SH_C0 * g.f_dc[order].astype(np.float64)  # [M, 3]

    out = np.empty(len(order), SPLAT_DTYPE)
    out["position"] = g.means[order]
    out["scale"] = scales[order]
    out["rgba"][:, :3] = np.clip(np.round(rgb * 255.0), 0, 255)
    out["rgba"][:, 3] = np.clip(np.round(opacity[order] * 255.0), 0, 255)
    out["rot"] = np.clip(np.round(q * 128.0 + 128.0), 0, 255)
    return out.tobytes()


def decode_splat(raw: bytes) -> np.ndarray:
    """View ``.splat`` bytes as a structured array of :data:`SPLAT_DTYPE` records."""
    if len(raw) % SPLAT_DTYPE.itemsize:
        raise ValueError(f".splat data length {len(raw)} is not a multiple of {SPLAT_DTYPE.itemsize}")
    return np.frombuffer(raw, SPLAT_DTYPE)


@dataclass
class PointCloud:
    positions: np.ndarray  # [N, 3] float32
    colors: np.ndarray  # [N, 3] uint8


def read_points_ply(path: str | os.PathLike, max_points: int | None = None, seed: int = 0) -> PointCloud:
    """Read x, y, z and (optional) red, green, blue from a point-cloud PLY; subsample to ``max_points``.

    Usage:
        pc = read_points_ply("ws/export/points.ply", max_points=100_000)
        pc.positions.dtype, pc.colors.dtype
    """
    cloud = read_point_cloud(path, "re-run `plantsplat export`")
    pos = cloud["xyz"].astype(np.float32)  # [N, 3]
    col = cloud["rgb"] if cloud["rgb"] is not None else np.full((len(pos), 3), 200, np.uint8)
    keep = np.isfinite(pos).all(1)
    pos, col = pos[keep], col[keep]
    if max_points is not None and len(pos) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(len(pos), max_points, replace=False))
        pos, col = pos[idx], col[idx]
    return PointCloud(np.ascontiguousarray(pos), np.ascontiguousarray(col))

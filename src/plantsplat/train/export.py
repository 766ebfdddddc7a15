"""Export a trained model: Inria-layout 3DGS PLY and a point cloud of opacity-filtered centres.

``export/splat.ply`` (binary little-endian, readable by the usual splat viewers and the Inria code):
``x y z nx ny nz f_dc_0..2 f_rest_0..M opacity scale_0..2 rot_0..3`` as float32, with opacity as a
logit, scales as logs and rotations as (w, x, y, z); ``f_rest`` channel-major as Inria's
(``f_rest_{c * (K-1) + k}``).

``export/points.ply``: centres with opacity >= ``min_opacity``: ``x y z`` float32, ``red green blue``
uchar (the DC colour), ``opacity`` float (0..1), ``scale_0..2`` float (cm). Coordinates are in the
workspace's calibrated frame (cm, z up).

Example:
    >>> files = export_workspace(Workspace("ws/plant_01"))  # doctest: +SKIP
    >>> g = read_splat_ply("ws/plant_01/export/splat.ply")  # doctest: +SKIP
    >>> g["means"].shape  # doctest: +SKIP
    (41210, 3)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import atomic_path
from plantsplat.log import get_logger
from plantsplat.workspace import Workspace

log = get_logger(__name__)


@dataclass
class ExportConfig:
    """Options of ``plantsplat export``."""

    min_opacity: float = 0.1
    """Centres with a lower opacity are left out of points.ply (the paper's culling threshold)."""
    train_dir: Path | None = None
    """Folder of the trained model (default WS/train)."""
    force: bool = False
    """Rewrite the PLYs even when they are newer than the model."""


def write_splat_ply(path: str | os.PathLike, means: np.ndarray, scales_log: np.ndarray, quats: np.ndarray,
                    opacity_logit: np.ndarray, sh0: np.ndarray, shN: np.ndarray) -> None:
    """Write Gaussians in the Inria layout (atomically).

    Args:
        means: ``[N, 3]``; scales_log: ``[N, 3]`` log scales; quats: ``[N, 4]`` wxyz;
        opacity_logit: ``[N]``; sh0: ``[N, 1, 3]``; shN: ``[N, K-1, 3]``.
    """
    from plyfile import PlyData, PlyElement

    n = len(means)
    f_dc = np.asarray(sh0, np.float32).reshape(n, 3)  # [N, 3]
    f_rest = np.asarray(shN, np.float32).transpose(0, 2, 1).reshape(n, -1)  # [N, 3*(K-1)] channel-major
    cols = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(f_rest.shape[1])] + ["opacity"]
            + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    data = np.concatenate([
        np.asarray(means, np.float32), np.zeros((n, 3), np.float32), f_dc, f_rest,
        np.asarray(opacity_logit, np.float32).reshape(n, 1), np.asarray(scales_log, np.float32),
        np.asarray(quats, np.float32),
    ], axis=1)
    rec = np.empty(n, dtype=[(c, "f4") for c in cols])
    for i, c in enumerate(cols):
        rec[c] = data[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], byte_order="<").write(str(tmp))


def read_splat_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read an Inria-layout 3DGS PLY into raw (not activated) arrays.

    Returns ``means [N, 3]``, ``scales [N, 3]`` (log), ``quats [N, 4]`` (wxyz), ``opacities [N]``
    (logit), ``sh0 [N, 1, 3]``, ``shN [N, K-1, 3]``.
    """
    from plyfile import PlyData

    path = Path(path)
    try:
        v = PlyData.read(str(path))["vertex"]
    except Exception as exc:
        raise PlantsplatError(f"{path}: unreadable PLY ({exc}); re-run `plantsplat export`") from exc
    names = v.data.dtype.names
    need = ["x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"]
    if any(c not in names for c in need):
        raise PlantsplatError(f"{path}: not a 3DGS PLY (needs {', '.join(need)}); export it with `plantsplat export`")
    col = lambda c: np.asarray(v[c], np.float32)  # noqa: E731
    n = len(v.data)
    rest = sorted((c for c in names if c.startswith("f_rest_")), key=lambda c: int(c.split("_")[-1]))
    if len(rest) % 3:
        raise PlantsplatError(f"{path}: {len(rest)} f_rest properties, not a multiple of 3")
    f_rest = np.stack([col(c) for c in rest], -1) if rest else np.zeros((n, 0), np.float32)
    return {
        "means": np.stack([col("x"), col("y"), col("z")], -1),
        "scales": np.stack([col(f"scale_{i}") for i in range(3)], -1),
        "quats": np.stack([col(f"rot_{i}") for i in range(4)], -1),
        "opacities": col("opacity"),
        "sh0": np.stack([col(f"f_dc_{i}") for i in range(3)], -1)[:, None, :],
        "shN": f_rest.reshape(n, 3, -1).transpose(0, 2, 1),
    }


def write_points_ply(path: str | os.PathLike, means: np.ndarray, rgb: np.ndarray, opacity: np.ndarray,
                     scales: np.ndarray) -> None:
    """Point cloud with ``x y z`` float32, ``red green blue`` uchar, ``opacity``, ``scale_0..2`` float."""
    from plyfile import PlyData, PlyElement

    n = len(means)
    dt = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
          ("opacity", "f4"), ("scale_0", "f4"), ("scale_1", "f4"), ("scale_2", "f4")]
    rec = np.empty(n, dtype=dt)
    for i, c in enumerate("xyz"):
        rec[c] = means[:, i]
    c8 = np.clip(np.round(np.asarray(rgb) * 255), 0, 255).astype(np.uint8)
    rec["red"], rec["green"], rec["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
    rec["opacity"] = opacity
    for i in range(3):
        rec[f"scale_{i}"] = scales[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], byte_order="<").write(str(tmp))


def export_workspace(ws: Workspace | str | os.PathLike, cfg: ExportConfig | None = None) -> dict:
    """Write ``export/splat.ply`` and ``export/points.ply`` from ``train/model.pt``; skipped when both
    are newer than the model (unless ``cfg.force``). Returns paths and counts."""
    import torch

    from plantsplat.train.model import SH_C0
    from plantsplat.train.trainer import load_model, model_path

    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    cfg = cfg or ExportConfig()
    if not 0.0 <= cfg.min_opacity < 1.0:
        raise PlantsplatError(f"--min-opacity {cfg.min_opacity}: must be in [0, 1)", exit_code=2)
    mp = model_path(ws, cfg.train_dir)
    outs = [ws.splat_ply, ws.points_ply]
    if (not cfg.force and mp.is_file() and all(p.is_file() for p in outs)
            and min(p.stat().st_mtime for p in outs) >= mp.stat().st_mtime):
        log.info("%s and %s are up to date; skipping (--force rewrites)", ws.splat_ply, ws.points_ply)
        return {"splat_ply": str(ws.splat_ply), "points_ply": str(ws.points_ply), "skipped": True}
    params, _ = load_model(ws, cfg.train_dir)
    p = {k: v.detach().cpu().numpy() for k, v in params.items()}
    quats = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True).clip(1e-12)
    write_splat_ply(ws.splat_ply, p["means"], p["scales"], quats, p["opacities"], p["sh0"], p["shN"])
    opacity = torch.sigmoid(torch.from_numpy(p["opacities"])).numpy()
    keep = opacity >= cfg.min_opacity
    rgb = p["sh0"][:, 0] * SH_C0 + 0.5
    write_points_ply(ws.points_ply, p["means"][keep], rgb[keep], opacity[keep], np.exp(p["scales"][keep]))
    log.info("wrote %s (%d Gaussians) and %s (%d centres with opacity >= %.2f)", ws.splat_ply, len(quats),
             ws.points_ply, int(keep.sum()), cfg.min_opacity)
    return {"splat_ply": str(ws.splat_ply), "points_ply": str(ws.points_ply), "n_gaussians": len(quats),
            "n_points": int(keep.sum()), "skipped": False}

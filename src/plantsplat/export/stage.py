"""The export stage over a workspace: what it reads (the trained model, ``WS/train/model.pt``), what it writes, and
:func:`run`: an Inria-layout 3DGS PLY and a point cloud of opacity-filtered centres.

``export/splat.ply`` (binary little-endian, readable by the usual splat viewers and the Inria code):
``x y z nx ny nz f_dc_0..2 f_rest_0..M opacity scale_0..2 rot_0..3`` as float32, with opacity as a
logit, scales as logs and rotations as (w, x, y, z); ``f_rest`` channel-major as Inria's
(``f_rest_{c * (K-1) + k}``).

``export/points.ply``: centres with opacity >= ``min_opacity``: ``x y z`` float32, ``red green blue``
uchar (the DC colour), ``opacity`` float (0..1), ``scale_0..2`` float (cm). Coordinates are in the
workspace's calibrated frame (cm, z up).

Usage:
    from plantsplat.export import ExportConfig, stage
    files = stage.run(Workspace("ws/plant_01"), ExportConfig())
    files["n_gaussians"], files["n_points"]
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from plantsplat.errors import PlantsplatError
from plantsplat.export.config import ExportConfig
from plantsplat.log import get_logger
from plantsplat.ply import write_point_cloud, write_splat
from plantsplat.train.checkpoint import load_model, model_path
from plantsplat.train.model import SH_C0
from plantsplat.workspace import Workspace

log = get_logger(__name__)


def inputs(ws: Workspace, cfg: ExportConfig) -> list[Path]:
    """The file the stage reads: the trained model (``cfg.train_dir`` or ``WS/train``)."""
    return [model_path(ws, cfg.train_dir)]


def outputs(ws: Workspace) -> list[Path]:
    """The files the stage writes."""
    return [ws.splat_ply, ws.points_ply]


def run(ws: Workspace | str | os.PathLike, cfg: ExportConfig | None = None) -> dict:
    """Run the export stage: write ``export/splat.ply`` and ``export/points.ply`` (each atomically) from the trained
    model; returns paths and counts.

    Usage:
        files = run(Workspace("ws/plant_01"), ExportConfig(min_opacity=0.2))
        files["points_ply"], files["n_points"]
    """
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    cfg = cfg or ExportConfig()
    if not 0.0 <= cfg.min_opacity < 1.0:
        raise PlantsplatError(f"--min-opacity {cfg.min_opacity}: must be in [0, 1)", exit_code=2)
    params, _ = load_model(ws, cfg.train_dir)
    p = {k: v.detach().cpu().numpy() for k, v in params.items()}
    quats = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True).clip(1e-12)
    write_splat(ws.splat_ply, p["means"], p["scales"], quats, p["opacities"], p["sh0"], p["shN"])
    opacity = torch.sigmoid(torch.from_numpy(p["opacities"])).numpy()
    keep = opacity >= cfg.min_opacity
    rgb = p["sh0"][:, 0] * SH_C0 + 0.5
    rgb8 = np.clip(np.round(rgb[keep] * 255), 0, 255).astype(np.uint8)
    write_point_cloud(ws.points_ply, p["means"][keep], rgb8, opacity=opacity[keep], scale=np.exp(p["scales"][keep]))
    log.info("wrote %s (%d Gaussians) and %s (%d centres with opacity >= %.2f)", ws.splat_ply, len(quats),
             ws.points_ply, int(keep.sum()), cfg.min_opacity)
    return {"splat_ply": str(ws.splat_ply), "points_ply": str(ws.points_ply), "n_gaussians": len(quats),
            "n_points": int(keep.sum())}

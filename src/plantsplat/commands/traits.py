"""`plantsplat traits WS`: plant traits (cm) from the exported point cloud."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.errors import EXIT_RESULT_FAILED
from plantsplat.io import read_json
from plantsplat.log import console
from plantsplat.pipeline import traits_stage
from plantsplat.traitdefs import TRAIT_KEYS
from plantsplat.traits.config import TraitsConfig
from plantsplat.workspace import Workspace


@dataclass
class TraitsCommand:
    """Measure the plant: DBSCAN clusters, the cube by its oriented bounding box and fitted face planes
    (scale cross-check or scale), height, PCA widths, canopy volume and area, fruit count.
    Writes WS/traits.json, WS/traits.csv and WS/traits.png. Exits with code 4 when the result failed its
    checks (traits.json says which; the files are written all the same)."""

    workspace: tyro.conf.Positional[Path]
    """Plant workspace folder (reads export/splat.ply, or export/points.ply with --extent-sigma 0,
    and poses.json)."""
    points: Path | None = None
    """Measure this PLY instead of the workspace's export: a splat.ply (its Gaussians' extents are sampled) or any
    point cloud (x, y, z; colours and opacity optional)."""
    calibrated: bool | None = None
    """Whether the cloud is in the ArUco-calibrated frame (cm, z up). Default: from WS/poses.json scale_source."""
    figure: bool = True
    """Write WS/traits.png (top view with PCA widths, side view with height)."""
    settings: Annotated[TraitsConfig, tyro.conf.arg(name="")] = field(default_factory=TraitsConfig)
    """Measurement settings."""
    force: bool = False
    """Measure again even when traits.json is up to date for these settings and this cloud."""


def run(cfg: TraitsCommand) -> int:
    ws = Workspace(cfg.workspace, must_exist=True)
    traits_stage(ws, cfg.settings, cfg.force, points=cfg.points, calibrated=cfg.calibrated, figure=cfg.figure)
    out = read_json(ws.traits_json)
    vals = "  ".join(
        f"{k}={out[k]:.2f}" if isinstance(out[k], float) else f"{k}={out[k]}"
        for k in TRAIT_KEYS
    )
    console.print(f"traits ({out['quality']}, scale: {out['scale'].get('source')}): {vals}", highlight=False)
    wrote = [ws.traits_json, ws.traits_csv, *([ws.traits_png] if cfg.figure else []),
             *([ws.plant_ply] if ws.plant_ply.is_file() else [])]
    console.print("wrote " + ", ".join(str(p) for p in wrote))
    return EXIT_RESULT_FAILED if out["quality"] == "failed" else 0


COMMAND = Command(
    name="traits",
    config=TraitsCommand,
    run=run,
    help="Plant traits (height, PCA widths, canopy volume/area, fruit count) from the point cloud.",
    order=60,
)

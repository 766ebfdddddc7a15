"""`plantsplat traits WS`: plant traits (cm) from the exported point cloud."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from plantsplat.commands import Command
from plantsplat.traits.measure import TraitSettings


@dataclass
class TraitsConfig:
    """Measure the plant: DBSCAN clusters, the cube by its oriented bounding box and fitted face planes
    (scale cross-check or scale), height, PCA widths, canopy volume and area, fruit count.
    Writes WS/traits.json, WS/traits.csv and WS/traits.png."""

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
    settings: TraitSettings = field(default_factory=TraitSettings)
    """Measurement settings."""


def run(cfg: TraitsConfig) -> int:
    from plantsplat.errors import UsageError
    from plantsplat.log import console
    from plantsplat.traits.measure import traits_workspace
    from plantsplat.workspace import Workspace

    if not cfg.workspace.is_dir():
        raise UsageError(f"{cfg.workspace}: workspace folder not found; give the folder made by `plantsplat frames`")
    s = cfg.settings
    if not 0 <= s.trim < 0.5:
        raise UsageError(f"--trim {s.trim}: must be in [0, 0.5)")
    if s.eps is not None and s.eps <= 0:
        raise UsageError(f"--eps {s.eps}: must be positive")
    if s.min_points < 1 or s.merge_distance_cm < 0 or s.cube_size_cm <= 0:
        raise UsageError("--min-points must be >= 1, --merge-distance-cm >= 0 and --cube-size-cm > 0")
    ws = Workspace(cfg.workspace)
    out = traits_workspace(ws, s, points_path=cfg.points, calibrated=cfg.calibrated, figure=cfg.figure)
    vals = "  ".join(
        f"{k}={out[k]:.2f}" if isinstance(out[k], float) else f"{k}={out[k]}"
        for k in ("height_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2", "fruit_count")
    )
    console.print(f"traits ({out['quality']}, scale: {out['scale'].get('source')}): {vals}", highlight=False)
    console.print(f"wrote {ws.traits_json}, {ws.traits_csv}" + (f", {ws.traits_png}" if cfg.figure else ""))
    return 0


COMMAND = Command(
    name="traits",
    config=TraitsConfig,
    run=run,
    help="Plant traits (height, PCA widths, canopy volume/area, fruit count) from the point cloud.",
    order=60,
)

"""`plantsplat export`: Inria-layout 3DGS PLY and an opacity-filtered point cloud."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from plantsplat.commands import Command
from plantsplat.train.export import ExportConfig


@dataclass
class ExportCommand:
    """Write WS/export/splat.ply (Inria 3DGS layout, for splat viewers) and WS/export/points.ply
    (Gaussian centres with opacity >= --min-opacity: x y z, red green blue, opacity, scale_0..2; cm, z up)."""

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    export: ExportConfig = field(default_factory=ExportConfig)


def run(cfg: ExportCommand) -> int:
    from plantsplat.errors import PlantsplatError
    from plantsplat.train import export_workspace
    from plantsplat.workspace import Workspace

    if not cfg.workspace.is_dir():
        raise PlantsplatError(f"{cfg.workspace}: no such workspace folder", exit_code=2)
    export_workspace(Workspace(cfg.workspace), cfg.export)
    return 0


COMMAND = Command(name="export", config=ExportCommand, run=run,
                  help="Export the trained Gaussians as a 3DGS PLY and a point-cloud PLY.", order=55)

"""`plantsplat export`: Inria-layout 3DGS PLY and an opacity-filtered point cloud."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.export.config import ExportConfig
from plantsplat.pipeline import export_stage
from plantsplat.workspace import Workspace


@dataclass
class ExportCommand:
    """Write WS/export/splat.ply (Inria 3DGS layout, for splat viewers) and WS/export/points.ply
    (Gaussian centres with opacity >= --min-opacity: x y z, red green blue, opacity, scale_0..2; cm, z up)."""

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    export: Annotated[ExportConfig, tyro.conf.arg(name="")] = field(default_factory=ExportConfig)
    force: bool = False
    """Write the PLYs again even when they are up to date."""


def run(cfg: ExportCommand) -> int:
    export_stage(Workspace(cfg.workspace, must_exist=True), cfg.export, cfg.force)
    return 0


COMMAND = Command(name="export", config=ExportCommand, run=run,
                  help="Export the trained Gaussians as a 3DGS PLY and a point-cloud PLY.", order=55)

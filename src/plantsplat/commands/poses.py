"""`plantsplat poses WS`: camera poses by COLMAP SfM (or import), calibrated in cm with the ArUco cube."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.pipeline import poses_stage
from plantsplat.poses.config import PosesConfig
from plantsplat.workspace import Workspace


@dataclass
class PosesCommand:
    """Estimate camera poses and sparse points for WS/images, in centimetres with z up (cube frame).

    Writes WS/sparse/0 (COLMAP binary), WS/sparse_text/0 (text), WS/transforms.json (nerfstudio),
    WS/sparse_points.ply and WS/poses.json (report). Re-running with the same options and frames reuses them.
    """

    workspace: tyro.conf.Positional[Path]
    """Workspace folder (with images/ from `plantsplat frames`)."""
    options: Annotated[PosesConfig, tyro.conf.arg(name="")] = field(default_factory=PosesConfig)
    """SfM, import and calibration options."""
    force: bool = False
    """Redo the stage even when its outputs are up to date."""


def run(cmd: PosesCommand) -> int:
    if logging.getLogger("plantsplat").isEnabledFor(logging.DEBUG):
        cmd.options.colmap_log = True
    poses_stage(Workspace(cmd.workspace, must_exist=True), cmd.options, cmd.force)
    return 0


COMMAND = Command(
    name="poses",
    config=PosesCommand,
    run=run,
    help="Camera poses (COLMAP SfM or import) calibrated in cm, z up, with the ArUco cube.",
    order=40,
)

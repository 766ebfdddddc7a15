"""`plantsplat segment`: plant + cube masks, RGBA images and a preview for a workspace's frames."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.pipeline import segment_stage
from plantsplat.segment.config import SegmentConfig
from plantsplat.workspace import Workspace


@dataclass
class SegmentCommand:
    """Cut the plant and the cube out of every frame: WS/masks/, WS/rgba/, segment.json, masks_preview.png.

    Runs after `plantsplat poses` (the plant is decided in 3D). Examples:
    plantsplat segment ws/plant01;  plantsplat segment ws/plant01 --import-masks my_sam2_masks/
    """

    workspace: tyro.conf.Positional[Path]
    """Workspace folder (after `plantsplat poses`)."""
    options: Annotated[SegmentConfig, tyro.conf.arg(name="")] = field(default_factory=SegmentConfig)
    """Segmenter options."""
    force: bool = False
    """Recompute even when the masks are up to date."""


def run(cmd: SegmentCommand) -> int:
    segment_stage(Workspace(cmd.workspace, must_exist=True), cmd.options, cmd.force)
    return 0


COMMAND = Command(
    name="segment",
    config=SegmentCommand,
    run=run,
    help="Plant + cube masks and RGBA images (decided in 3D, or SAM-2, or your own masks).",
    order=45,
)

"""`plantsplat frames`: video or image folder -> sharp, spread-out frames in WS/images/."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.frames.config import FramesConfig
from plantsplat.pipeline import frames_stage
from plantsplat.workspace import Workspace


@dataclass
class FramesCommand:
    """Choose sharp frames spread over a video (or image folder) and write them to WS/images/.

    Example: plantsplat frames plant01.mov --out ws/plant01 --num 120 --max-size 960
    """

    input: tyro.conf.Positional[Path]
    """Video file (mp4/mov, H.264 or HEVC; phone rotation honoured) or a folder of images."""
    out: Path
    """Workspace folder to write images/ and frames.json into (created if missing)."""
    options: Annotated[FramesConfig, tyro.conf.arg(name="")] = field(default_factory=FramesConfig)
    """Frame selection."""
    force: bool = False
    """Extract again even when the frames are up to date, or replace images/ this stage did not write."""


def run(cmd: FramesCommand) -> int:
    frames_stage(Workspace(cmd.out), cmd.input, cmd.options, cmd.force)
    return 0


COMMAND = Command(
    name="frames",
    config=FramesCommand,
    run=run,
    help="Video or image folder -> sharp frames spread over the capture (WS/images/).",
    order=20,
)

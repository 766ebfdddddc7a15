"""`plantsplat report WS`: one self-contained HTML report of a plant workspace, with a 3D splat viewer."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.errors import UsageError
from plantsplat.log import get_logger
from plantsplat.report.config import ReportConfig


@dataclass
class ReportCommand:
    """Write WS/report.html: traits and measurement figure, interactive 3D view of the Gaussian splat and
    point cloud, test-view renders beside ground truth, image metrics, frames with masks, camera path,
    run times. Parts that do not exist yet are named in the report. Opens offline from file://."""

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    out: Path | None = None
    """Where to write the report (default: WS/report.html)."""
    options: Annotated[ReportConfig, tyro.conf.arg(name="")] = field(default_factory=ReportConfig)


def run(cfg: ReportCommand) -> int:
    from plantsplat.report.plant import write_report  # deferred: it loads OpenCV and matplotlib

    for name in ("max_gaussians", "max_points", "max_frames", "max_render_pairs"):
        if getattr(cfg.options, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(cfg.options, name)}")
    path = write_report(cfg.workspace, cfg.out, cfg.options)
    get_logger(__name__).info("open %s in a browser (works offline)", path.resolve().as_uri())
    print(path)
    return 0


COMMAND = Command(name="report", config=ReportCommand, run=run, help="Write an HTML report with a 3D splat viewer.",
                  order=90)

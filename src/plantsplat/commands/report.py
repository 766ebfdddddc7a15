"""`plantsplat report WS`: one self-contained HTML report of a plant workspace, with a 3D splat viewer."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from plantsplat.commands import Command


@dataclass
class ReportConfig:
    """Write WS/report.html: traits and measurement figure, interactive 3D view of the Gaussian splat and
    point cloud, test-view renders beside ground truth, image metrics, frames with masks, camera path,
    run times. Parts that do not exist yet are named in the report. Opens offline from file://."""

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    out: Path | None = None
    """Where to write the report (default: WS/report.html)."""
    max_gaussians: int = 250_000
    """Keep at most this many Gaussians (the most visible) in the 3D viewer; 32 bytes each."""
    max_points: int = 100_000
    """Keep at most this many points in the point-cloud view."""
    max_frames: int = 24
    """Frames in the contact sheet."""
    viewer: bool = True
    """Include the interactive 3D viewer (about 3.2 MB of JavaScript); --no-viewer leaves it out."""


def run(cfg: ReportConfig) -> int:
    from plantsplat.errors import UsageError
    from plantsplat.log import get_logger
    from plantsplat.report import ReportOptions, write_report

    for name in ("max_gaussians", "max_points", "max_frames"):
        if getattr(cfg, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(cfg, name)}")
    opts = ReportOptions(max_gaussians=cfg.max_gaussians, max_points=cfg.max_points, max_frames=cfg.max_frames,
                         viewer=cfg.viewer)
    path = write_report(cfg.workspace, cfg.out, opts)
    get_logger(__name__).info("open %s in a browser (works offline)", path.resolve().as_uri())
    print(path)
    return 0


COMMAND = Command(name="report", config=ReportConfig, run=run, help="Write an HTML report with a 3D splat viewer.",
                  order=90)

"""Options of the plant report (light: nothing heavy is imported here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ReportConfig:
    """What goes into the report and how big it may get."""

    max_gaussians: int = 250_000
    """Keep at most this many Gaussians (the most visible) in the 3D viewer (32 bytes each)."""
    max_points: int = 100_000
    """Keep at most this many points of export/points.ply in the point-cloud view (15 bytes each)."""
    max_frames: int = 24
    """Frames in the contact sheet (spread evenly over the capture)."""
    max_render_pairs: int = 8
    """Test views shown as render / ground-truth pairs."""
    viewer: bool = True
    """Include the interactive 3D viewer (adds about 3.2 MB of JavaScript)."""

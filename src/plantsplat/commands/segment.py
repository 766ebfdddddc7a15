"""`plantsplat segment`: plant + cube masks, RGBA images and a preview for a workspace's frames."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from plantsplat.commands import Command


@dataclass
class SegmentConfig:
    """Cut the plant and the cube out of every frame: WS/masks/, WS/rgba/, segment.json, masks_preview.png.

    Example: plantsplat segment ws/plant01 [--backend sam2 --sam2-checkpoint sam2.1_hiera_tiny.pt]
    """

    workspace: tyro.conf.Positional[Path]
    """Workspace folder (after `plantsplat frames`)."""
    backend: Literal["classic", "sam2"] = "classic"
    """`classic`: offline, no model (plant colours + cube geometry + multi-view hull); `sam2`: SAM-2 video predictor prompted from the classic result."""
    sam2_checkpoint: Path | None = None
    """SAM-2 checkpoint file (e.g. sam2.1_hiera_tiny.pt) for --backend sam2."""
    sam2_config: str | None = None
    """SAM-2 config name (default: guessed from the checkpoint name, e.g. configs/sam2.1/sam2.1_hiera_t.yaml)."""
    device: str | None = None
    """Torch device for SAM-2 (default: cuda when available, else cpu)."""
    no_cube: bool = False
    """Ignore the marker cube (no cube silhouette, 2D plant locator): for captures without a cube."""
    keep_pot: bool = False
    """Keep a plant-coloured (green/red) pot in the masks; by default it is found in 3D (a solid block on the ground) and left out."""
    max_excluded: float = 0.5
    """Fail (writing nothing) when more than this fraction of frames has no plant."""
    force: bool = False
    """Recompute even when the masks are up to date."""


def run(cfg: SegmentConfig) -> int:
    from plantsplat.segment import segment_workspace
    from plantsplat.segment.classic import ClassicSettings
    from plantsplat.workspace import Workspace

    segment_workspace(
        Workspace(cfg.workspace),
        backend=cfg.backend,
        force=cfg.force,
        sam2_checkpoint=cfg.sam2_checkpoint,
        sam2_config=cfg.sam2_config,
        settings=ClassicSettings(use_cube=not cfg.no_cube, remove_pot=not cfg.keep_pot),
        max_excluded=cfg.max_excluded,
        device=cfg.device,
    )
    return 0


COMMAND = Command(
    name="segment",
    config=SegmentConfig,
    run=run,
    help="Plant + cube masks and RGBA images (classic offline segmenter, or SAM-2).",
    order=30,
)

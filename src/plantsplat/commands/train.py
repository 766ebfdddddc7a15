"""`plantsplat train`: object-centric (or full-frame) 3D Gaussian Splatting on a workspace."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from plantsplat.commands import Command
from plantsplat.train.config import TrainConfig


@dataclass
class TrainCommand:
    """Train a 3DGS model on WS/images, WS/masks and the calibrated poses; resumes an interrupted run.

    Writes WS/train/ (split.json, checkpoint.pt while running, model.pt, config.json) and WS/metrics.json
    (PSNR/SSIM/LPIPS on the test views, full frame and foreground only, render FPS, Gaussians, time, memory).
    """

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    train: TrainConfig = field(default_factory=TrainConfig)


def run(cfg: TrainCommand) -> int:
    from plantsplat.errors import PlantsplatError
    from plantsplat.train import train_workspace
    from plantsplat.workspace import Workspace

    if not cfg.workspace.is_dir():
        raise PlantsplatError(f"{cfg.workspace}: no such workspace folder", exit_code=2)
    train_workspace(Workspace(cfg.workspace), cfg.train)
    return 0


COMMAND = Command(name="train", config=TrainCommand, run=run,
                  help="Train the object-centric 3DGS model (or the full-frame baseline).", order=50)

"""`plantsplat train`: object-centric (or full-frame) 3D Gaussian Splatting on a workspace."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.pipeline import train_stage
from plantsplat.train.config import TrainConfig
from plantsplat.workspace import Workspace


@dataclass
class TrainCommand:
    """Train a 3DGS model on WS/images, WS/masks and the calibrated poses; resumes an interrupted run.

    Writes WS/train/ (split.json, model.pt, config.json; trained in WS/.train.partial/, which replaces it whole
    when complete, so an interrupted or failed run keeps the previous model) and WS/metrics.json
    (PSNR/SSIM/LPIPS on the test views, full frame and foreground only, render FPS, Gaussians, time, memory).
    """

    workspace: tyro.conf.Positional[Path]
    """The plant's workspace folder."""
    train: Annotated[TrainConfig, tyro.conf.arg(name="")] = field(default_factory=TrainConfig)
    force: bool = False
    """Train afresh even when the model is up to date for these options, frames, masks and poses."""


def run(cfg: TrainCommand) -> int:
    train_stage(Workspace(cfg.workspace, must_exist=True), cfg.train, cfg.force)
    return 0


COMMAND = Command(name="train", config=TrainCommand, run=run,
                  help="Train the object-centric 3DGS model (or the full-frame baseline).", order=50)

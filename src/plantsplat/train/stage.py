"""The train stage over a workspace: what it reads, what it writes, and :func:`run`.

It reads the frames, the segment stage's masks and record and the poses stage's cameras; it writes the trained
model, its configuration and its split in ``WS/train/`` (or ``cfg.train_dir``) and, with ``cfg.evaluate``, the
image metrics of the test views (``WS/metrics.json``). The loop itself (trained in ``WS/.train.partial/``, which
replaces ``WS/train/`` whole when complete) is :func:`plantsplat.train.trainer.train_workspace`; the metrics,
:mod:`plantsplat.train.evaluate`.

Usage:
    from plantsplat.train import TrainConfig, stage
    summary = stage.run(Workspace("ws/plant_01"), TrainConfig(iterations=500))
    summary["n_gaussians"]
"""

from __future__ import annotations

import os
from pathlib import Path

from plantsplat.train.checkpoint import train_paths
from plantsplat.train.config import TrainConfig
from plantsplat.train.trainer import train_workspace
from plantsplat.workspace import Workspace


def inputs(ws: Workspace, cfg: TrainConfig) -> list[Path]:
    """The files and folders the stage reads: the frames, their masks and the cameras."""
    return [ws.images_dir, ws.masks_dir, ws.segment_json, ws.sparse_dir, ws.transforms_json]


def outputs(ws: Workspace, cfg: TrainConfig) -> list[Path]:
    """The files the stage writes: the model, its configuration and split (in ``cfg.train_dir``, default
    ``WS/train``) and, with ``cfg.evaluate``, the metrics."""
    paths = train_paths(ws, cfg)
    return [paths["model"], paths["config"], paths["split"]] + ([paths["metrics"]] if cfg.evaluate else [])


def run(ws: Workspace | str | os.PathLike, cfg: TrainConfig | None = None, resume: bool = False) -> dict:
    """Run the train stage: train a 3DGS model of the workspace (``resume``: go on from the checkpoint of an
    interrupted run with the same options and inputs); returns the training summary.

    Whether the stage needs to run at all, and whether it resumes, is decided by
    :func:`plantsplat.pipeline.train_stage`.

    Usage:
        summary = run(Workspace("ws/plant_01"), TrainConfig(mode="object"))
        summary["n_gaussians"], summary["metrics"]
    """
    return train_workspace(ws if isinstance(ws, Workspace) else Workspace(ws), cfg or TrainConfig(), resume)

"""Object-centric 3D Gaussian Splatting: data, model, density control, training loop, metrics.

Library API (each call does its work; :mod:`plantsplat.pipeline` decides when a stage needs to run):

    from plantsplat.train import TrainConfig, train_workspace
    summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))

The trained model is exported by its own stage, :mod:`plantsplat.export`.

Submodules: ``config`` (options, presets), ``data`` (cameras, frames, split, initial points),
``model`` (parameters), ``checkpoint`` (checkpoints, the finished model), ``render`` (rendering, image
cache), ``loss``, ``strategy`` (density control), ``trainer`` (the loop),
``evaluate`` and ``metrics`` (PSNR/SSIM/LPIPS), ``romi`` (ROMI importer).
Heavy libraries load on first use, so importing the package stays cheap.
"""

from __future__ import annotations

from plantsplat.train.config import TrainConfig


def train_workspace(ws, cfg: TrainConfig | None = None, resume: bool = False) -> dict:
    """Train (or resume an interrupted run); see :func:`plantsplat.train.trainer.train_workspace`."""
    from plantsplat.train.trainer import train_workspace as _train

    return _train(ws, cfg, resume)


def evaluate_workspace(ws, **kwargs) -> dict:
    """Image metrics on the test views; see :func:`plantsplat.train.evaluate.evaluate_workspace`."""
    from plantsplat.train.evaluate import evaluate_workspace as _eval

    return _eval(ws, **kwargs)


__all__ = ["TrainConfig", "train_workspace", "evaluate_workspace"]

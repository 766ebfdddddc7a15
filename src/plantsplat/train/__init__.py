"""Object-centric 3D Gaussian Splatting: data, model, density control, training loop, metrics, export.

Library API (each call does its work; :mod:`plantsplat.pipeline` decides when a stage needs to run):

    from plantsplat.train import TrainConfig, train_workspace, export_workspace
    summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))
    files = export_workspace("ws/plant_01")

Submodules: ``config`` (options, presets), ``data`` (cameras, frames, split, initial points),
``model`` (parameters), ``checkpoint`` (checkpoints, the finished model), ``render`` (rendering, image
cache), ``loss``, ``strategy`` (density control), ``trainer`` (the loop),
``evaluate`` and ``metrics`` (PSNR/SSIM/LPIPS), ``export`` (PLY), ``romi`` (ROMI importer).
Heavy libraries load on first use, so importing the package stays cheap.
"""

from __future__ import annotations

from plantsplat.train.config import TrainConfig


def train_workspace(ws, cfg: TrainConfig | None = None, resume: bool = False) -> dict:
    """Train (or resume an interrupted run); see :func:`plantsplat.train.trainer.train_workspace`."""
    from plantsplat.train.trainer import train_workspace as _train

    return _train(ws, cfg, resume)


def export_workspace(ws, cfg=None) -> dict:
    """Write ``export/splat.ply`` and ``export/points.ply``; see :mod:`plantsplat.train.export`."""
    from plantsplat.train.export import ExportConfig
    from plantsplat.train.export import export_workspace as _export

    return _export(ws, cfg or ExportConfig())


def evaluate_workspace(ws, **kwargs) -> dict:
    """Image metrics on the test views; see :func:`plantsplat.train.evaluate.evaluate_workspace`."""
    from plantsplat.train.evaluate import evaluate_workspace as _eval

    return _eval(ws, **kwargs)


__all__ = ["TrainConfig", "train_workspace", "export_workspace", "evaluate_workspace"]

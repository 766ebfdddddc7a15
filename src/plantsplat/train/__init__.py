"""Object-centric 3D Gaussian Splatting: data, model, density control, training loop, metrics, export.

Library API (each call skips work already done, so re-running resumes):

    >>> from plantsplat.train import TrainConfig, train_workspace, export_workspace
    >>> summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))  # doctest: +SKIP
    >>> files = export_workspace("ws/plant_01")  # doctest: +SKIP

Submodules: ``config`` (options, presets), ``data`` (cameras, frames, split, initial points),
``model`` (parameters, checkpoints), ``strategy`` (density control), ``trainer`` (the loop),
``evaluate`` and ``metrics`` (PSNR/SSIM/LPIPS), ``export`` (PLY), ``romi`` (ROMI importer).
Heavy libraries load on first use, so importing the package stays cheap.
"""

from __future__ import annotations

from plantsplat.train.config import TrainConfig


def train_workspace(ws, cfg: TrainConfig | None = None) -> dict:
    """Train, resume or skip; see :func:`plantsplat.train.trainer.train_workspace`."""
    from plantsplat.train.trainer import train_workspace as _train

    return _train(ws, cfg)


def export_workspace(ws, cfg=None) -> dict:
    """Write ``export/splat.ply`` and ``export/points.ply``; see :mod:`plantsplat.train.export`."""
    from plantsplat.train.export import ExportConfig, export_workspace as _export

    return _export(ws, cfg or ExportConfig())


def evaluate_workspace(ws, **kwargs) -> dict:
    """Image metrics on the test views; see :func:`plantsplat.train.evaluate.evaluate_workspace`."""
    from plantsplat.train.evaluate import evaluate_workspace as _eval

    return _eval(ws, **kwargs)


TrainOptions = TrainConfig  # the name the end-to-end runner uses

__all__ = ["TrainConfig", "TrainOptions", "train_workspace", "export_workspace", "evaluate_workspace"]

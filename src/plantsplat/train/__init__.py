"""Object-centric 3D Gaussian Splatting: data, model, density control, training loop, metrics, export.

Library API (each call skips work already done, so re-running resumes):

    >>> from plantsplat.train import TrainConfig, train_workspace, export_workspace
    >>> summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))  # doctest: +SKIP
    >>> files = export_workspace("ws/plant_01")  # doctest: +SKIP
"""

from __future__ import annotations

from plantsplat.train.trainer import TrainConfig, load_model, train_workspace


def export_workspace(ws, cfg=None) -> dict:
    """Write ``export/splat.ply`` and ``export/points.ply`` (see :mod:`plantsplat.train.export`)."""
    from plantsplat.train.export import ExportConfig, export_workspace as _export

    return _export(ws, cfg or ExportConfig())


__all__ = ["TrainConfig", "train_workspace", "export_workspace", "load_model"]

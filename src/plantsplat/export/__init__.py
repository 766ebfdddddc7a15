"""Export: a trained Gaussian model as an Inria-layout 3DGS PLY and a point cloud of opacity-filtered centres.

The stage's settings are :mod:`plantsplat.export.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.export.stage` (it loads torch, so it is imported when it runs).

Usage:
    from plantsplat.export import ExportConfig, stage
    files = stage.run("ws/plant_01", ExportConfig(min_opacity=0.1))
"""

from plantsplat.export.config import ExportConfig

__all__ = ["ExportConfig"]

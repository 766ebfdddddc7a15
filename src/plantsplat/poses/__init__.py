"""Camera poses: COLMAP SfM through pycolmap, ArUco-cube metric calibration, COLMAP/nerfstudio interop.

The stage's settings are :mod:`plantsplat.poses.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.poses.stage`.

Usage:
    from plantsplat.poses import PosesConfig, stage
    report = stage.run("ws/plant_01", PosesConfig(matcher="exhaustive"))
"""

from plantsplat.poses.config import PosesConfig

__all__ = ["PosesConfig"]

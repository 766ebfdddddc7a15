"""Camera poses: COLMAP SfM through pycolmap, ArUco-cube metric calibration, COLMAP/nerfstudio interop.

Example:
    >>> from plantsplat.poses import PosesConfig, estimate_poses
    >>> report = estimate_poses("ws/plant_01", PosesConfig(matcher="exhaustive"))  # doctest: +SKIP
"""

from plantsplat.poses.estimate import PosesConfig, estimate_poses, outputs

__all__ = ["PosesConfig", "estimate_poses", "outputs"]

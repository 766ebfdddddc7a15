"""Camera poses: COLMAP SfM through pycolmap, ArUco-cube metric calibration, COLMAP/nerfstudio interop.

Usage:
    from plantsplat.poses import PosesConfig, estimate_poses
    report = estimate_poses("ws/plant_01", PosesConfig(matcher="exhaustive"))
"""

from plantsplat.poses.estimate import PosesConfig, estimate_poses, outputs

__all__ = ["PosesConfig", "estimate_poses", "outputs"]

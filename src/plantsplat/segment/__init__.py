"""Foreground segmentation (plant + cube) of a workspace's frames: masks, RGBA images, a preview, a report.

The stage's settings are :mod:`plantsplat.segment.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.segment.stage` (it loads torch and OpenCV, so it is imported when it runs).
The plant is decided in 3D (:mod:`~plantsplat.segment.object3d`, :mod:`~plantsplat.segment.decide`) in a quick
whole-scene model (:mod:`~plantsplat.segment.scene`) and drawn into each frame (:mod:`~plantsplat.segment.frame`);
SAM-2 (:mod:`~plantsplat.segment.sam2_backend`) and your own masks (:mod:`~plantsplat.segment.imports`) are the
other sources of masks.

Usage:
    from plantsplat.segment import SegmentConfig, stage
    info = stage.run("ws/plant01", SegmentConfig())
"""

from plantsplat.segment.config import SegmentConfig

__all__ = ["SegmentConfig"]

"""Plant traits from a reconstruction: clustering, cube calibration by plane fitting, measurement,
figures and accuracy statistics.

The stage's settings are :mod:`plantsplat.traits.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.traits.stage`. The measurement of any point cloud is
:func:`plantsplat.traits.measure.measure_traits`; accuracy against ground truth, :mod:`plantsplat.traits.stats`.
Both load SciPy and Open3D, so they are imported where they are used.

Usage:
    from plantsplat.traits.measure import measure_traits
    res = measure_traits(points, colors, calibrated=True)
    res.traits["height_cm"], res.quality
"""

from plantsplat.traits.config import TraitsConfig

__all__ = ["TraitsConfig"]

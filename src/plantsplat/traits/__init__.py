"""Plant traits from a reconstruction: clustering, cube calibration by plane fitting, measurement,
figures and accuracy statistics.

Usage:
    from plantsplat.traits import measure_traits, accuracy_table
    res = measure_traits(points, colors, calibrated=True)
    res.traits["height_cm"], res.quality
"""

from plantsplat.traits.config import TraitsConfig
from plantsplat.traits.measure import measure_traits
from plantsplat.traits.result import TraitResult
from plantsplat.traits.stats import (
    accuracy_table,
    format_table,
    scatter_plots,
    trait_metrics,
)

__all__ = [
    "TraitResult",
    "TraitsConfig",
    "accuracy_table",
    "format_table",
    "measure_traits",
    "scatter_plots",
    "trait_metrics",
]

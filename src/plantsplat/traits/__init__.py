"""Plant traits from a reconstruction: clustering, cube calibration by plane fitting, measurement,
figures and accuracy statistics.

Example:
    >>> from plantsplat.traits import measure_traits, accuracy_table
    >>> res = measure_traits(points, colors, calibrated=True)        # doctest: +SKIP
    >>> res.traits["height_cm"], res.quality                          # doctest: +SKIP
"""

from plantsplat.traits.measure import (
    TraitResult,
    TraitSettings,
    measure_traits,
    read_points_ply,
    traits_workspace,
)
from plantsplat.traits.stats import accuracy_table, format_table, scatter_plots, trait_metrics

__all__ = [
    "TraitResult",
    "TraitSettings",
    "accuracy_table",
    "format_table",
    "measure_traits",
    "read_points_ply",
    "scatter_plots",
    "trait_metrics",
    "traits_workspace",
]

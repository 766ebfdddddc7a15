"""The height's bounds: the interval the soil can lie in, widened by the scale's uncertainty.

A height from the soil is only as sure as the soil. Where the soil was seen in the pot (the segment
stage's quick model, or the SfM points), it lies within the band of slabs it was seen in (within half a
slab of the one slab that saw it), and is taken at the band's middle: a soil seen at grazing angles is
drawn as a layer some slabs thick. Where the
leaves hide it, everything that holds in any pot still bounds it: it lies no higher than the rim and
no higher than the plant's lowest point over the pot's inside (nothing of the plant grows below the
soil), and no lower than the ground the pot stands on. The height the traits give is measured from
the highest soil those allow (the shortest height the evidence permits); its bounds are the top of
the plant above both ends of the interval, each widened by two standard errors of the cube's scale.
A plant whose base was found in the pot (below its rim) has that base on the soil; one that does not
reach into the pot lost its base, and its height is not given as usable (:mod:`plantsplat.traits.checks`).

Example:
    >>> b = height_bounds(top_z=30.0, soil=SoilInterval(9.75, 10.25, "seen"), scale_se=0.002)
    >>> [round(v, 2) for v in b]
    [19.67, 20.33]
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SoilInterval:
    """Where the soil can lie (cm, cube frame): from ``low`` to ``high``; ``how`` it was bounded; for soil not seen,
    how far the plant reaches below the rim into the pot (``into_pot``, cm) and how its lowest centimetre there
    spreads (``base_spread``, see :class:`~plantsplat.traits.result.TraitResult`); None where it was seen."""

    low: float
    high: float
    how: str
    into_pot: float | None = None
    base_spread: float | None = None


def soil_interval(soil_z: float, seen: bool, resolution_cm: float, lowest_inside: float | None,
                  base_spread: float | None = None) -> SoilInterval:
    """The soil's interval: ``soil_z`` within half of ``resolution_cm`` where it was ``seen``; else from the ground (0)
    to the lower of ``soil_z`` (the rim) and the plant's lowest point over the pot's inside (``lowest_inside``), with
    how that lowest part spreads (``base_spread``)."""
    if seen:
        return SoilInterval(soil_z - resolution_cm / 2, soil_z + resolution_cm / 2, "seen")
    high = soil_z if lowest_inside is None else min(soil_z, lowest_inside)
    return SoilInterval(0.0, max(high, 0.0), "not seen: between the ground and the plant's lowest point in the pot",
                        into_pot=soil_z - high, base_spread=base_spread)


def height_bounds(top_z: float, soil: SoilInterval | None, scale_se: float | None, extent: float | None = None
                  ) -> tuple[float, float]:
    """``(low, high)`` of the plant's height (cm): its ``top_z`` above the ``soil`` interval, or its ``extent``
    without a soil, each end widened by two standard errors (``scale_se``, a fraction) of the scale."""
    lo, hi = (extent, extent) if soil is None else (top_z - soil.high, top_z - soil.low)
    k = 2.0 * (scale_se or 0.0)
    return lo * (1.0 - k), hi * (1.0 + k)

"""What the measurement found: :class:`TraitResult` (the traits, the scale, the cube, the clusters and why the
quality is what it is) and :func:`failed_result` for a cloud that could not be measured."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from plantsplat import traitdefs
from plantsplat.traits.config import ROBUST_KEYS, TraitsConfig


@dataclass
class TraitResult:
    """What :func:`measure_traits` found. ``traits`` holds None where a value could not be trusted."""

    traits: dict[str, float | int | None]
    robust: dict[str, float | None]
    quality: str
    """'ok', 'warning' (values given, see reasons) or 'failed' (no values)."""
    reasons: list[str]
    scale: dict
    cube: dict | None
    clusters: dict
    settings: dict
    plant_points: np.ndarray | None = None
    """[M, 3] the plant's points in the calibrated frame (cm, z up)."""
    plant_colors: np.ndarray | None = None
    """[M, 3] uint8 or None."""
    plant_centres: np.ndarray | None = None
    """[M, 3] the centre of the Gaussian each plant point was sampled from (calibrated frame); None when the cloud's
    points are not the Gaussians' extent samples."""
    plant_gaussians: np.ndarray | None = None
    """[G] sorted indices of the Gaussians whose centres lie on the plant (in the order of the cloud's centres); None
    when the cloud's points are not the Gaussians' extent samples."""
    cube_points: np.ndarray | None = None
    """[K, 3] the cube's points in the calibrated frame."""
    fruit_centres: np.ndarray | None = None
    """[F, 3] centres of the counted fruit."""
    transform: np.ndarray | None = None
    """[4, 4] cloud -> calibrated frame (similarity)."""
    timings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """Informational messages that do not lower the quality."""
    soil_z: float | None = None
    """Height of the soil surface the height is measured from (cm, calibrated frame); None: the plant's extent."""
    base_spread: float | None = None
    """Soil not seen: how the plant's lowest centimetre in the pot spreads over its inside (RMS distance from the
    axis over the inside's radius); None otherwise."""

    def to_json(self) -> dict:
        """The ``traits.json`` content (without the point arrays)."""
        out: dict = {k: self.traits.get(k) for k in traitdefs.TRAIT_KEYS}
        out.update(
            {
                "units": traitdefs.TRAIT_UNITS,
                "quality": self.quality,
                "quality_reasons": self.reasons,
                "scale_source": self.scale.get("source"),
                "soil_z_cm": self.soil_z,
                "notes": self.notes,
                "robust": {k: self.robust.get(k) for k in ROBUST_KEYS} | {"trim": self.settings.get("trim")},
                "method": (
                    "DBSCAN (Open3D) clustering; cube = cluster with a cube-like oriented bounding box, axes from "
                    "RANSAC+least-squares planes of its faces, edge from the distance between opposite planes or, "
                    "for Gaussians, the 1-99 % envelope along the axes (scale.cube_edge_method); points = Gaussian "
                    "centres plus their axis ends at settings.extent_sigma; plant = largest other cluster plus nearby "
                    "clusters; height = top above the soil (soil_z_cm; the z extent without a soil), height_extent = z "
                    "extent, widths = extents along the PCA axes of the ground-projected points, "
                    "canopy volume/area = 3D/2D convex hull, fruit = clusters of red points"
                ),
                "scale": self.scale,
                "cube": self.cube,
                "clusters": self.clusters,
                "fruit_count_definition": "ripe (red) fruit: clusters of plant points whose colour is within "
                f"{self.settings.get('fruit_hue_deg')} deg of red hue, saturation >= "
                f"{self.settings.get('fruit_min_saturation')}, value >= {self.settings.get('fruit_min_value')}; "
                "unripe (white/green) fruit are not counted",
                "fruit_centres_cm": None if self.fruit_centres is None else np.round(self.fruit_centres, 3).tolist(),
                "transform_to_cm": None if self.transform is None else self.transform.tolist(),
                "settings": self.settings,
                "timings_s": self.timings,
            }
        )
        return out


def failed_result(reason: str, settings: TraitsConfig, scale: dict | None = None, **kw) -> TraitResult:
    """A result with no traits, marked failed for ``reason``."""
    return TraitResult(
        traits={k: None for k in traitdefs.TRAIT_KEYS},
        robust={k: None for k in ROBUST_KEYS},
        quality="failed",
        reasons=[reason],
        scale=scale or {"source": None},
        cube=kw.pop("cube", None),
        clusters=kw.pop("clusters", {}),
        settings=asdict(settings),
        **kw,
    )

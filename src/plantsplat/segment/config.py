"""Options of the segment stage (one source for `plantsplat segment`, `run` and the library)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal


@dataclass
class SegmentConfig:
    """How the plant and the cube are cut out of every frame."""

    backend: Literal["3d", "sam2"] = "3d"
    """3d: the object decided in 3D from a quick whole-scene model, outlines refined on each frame (offline, no
    weights); sam2: SAM-2's video predictor prompted from the 3d masks (needs --sam2-checkpoint)."""
    import_masks: Path | None = None
    """Use your own masks from this folder instead (one image per frame, same name and size; 255 of 0/255 or 1 of
    0/1 masks = plant or cube; RGBA images give their alpha), as nerfstudio reads mask_path."""
    sam2_checkpoint: Path | None = None
    """SAM-2 checkpoint file (e.g. sam2.1_hiera_tiny.pt) for --backend sam2."""
    sam2_config: str | None = None
    """SAM-2 config name (default: guessed from the checkpoint name, e.g. configs/sam2.1/sam2.1_hiera_t.yaml)."""
    device: str | None = None
    """Torch device for SAM-2 (default: cuda when available, else cpu)."""
    scene_resolution: int = 360
    """Longest side (px) of the frames the quick whole-scene model is trained on."""
    scene_steps: int = 1600
    """Training steps of the quick whole-scene model."""
    scene_max_gaussians: int = 40_000
    """Cap on the quick model's Gaussians (it only has to place things, not render them well)."""
    min_in_view: float = 0.85
    """A plant Gaussian lies inside the frames of at least this share of the cameras (the plant is filmed all round)."""
    sfm_reach: float = 0.07
    """A plant Gaussian lies within this share of the cameras' distance from the axis of an SfM point."""
    weigh_evidence: bool = True
    """Decide the plant among the Gaussians in its region by their colours and neighbours as well (a minimum cut
    in 3D, see plantsplat.segment.decide); off: every Gaussian in the region is plant (position alone)."""
    refine_band_px: int = 6
    """Outlines are refined on each frame (GrabCut) within this many pixels of the 3D outline; 0 = not refined."""
    min_plant_fraction: float = 5e-4
    """A frame whose mask covers less than this share of the image has no plant: it is listed and left out of training."""
    max_excluded: float = 0.5
    """Fail (writing nothing) when more than this share of the frames has no plant."""
    preview: bool = True
    """Write masks_preview.png (masks over their frames, least sure first, with the segmenter's confidence) and, for the
    3d backend, segment_decision.png (the 3D decision)."""
    seed: int = 0
    """Random seed of the quick model."""

"""Options of a synthetic capture (light: no rendering library is imported here)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

FORMAT = "plantsplat-synth/1"


@dataclass
class SynthConfig:
    """Render a synthetic phone capture of a potted strawberry (with a 10 cm ArUco cube) and its exact ground truth."""

    out: Path
    """Output folder (must be empty or absent unless --force)."""
    seed: int = 0
    """Random seed: the plant, pot, room, lights, camera path and sensor noise all follow from it."""
    frames: int = 120
    """Number of video frames (the camera circles the plant three times: low, mid and high ring)."""
    width: int = 540
    """Frame width in pixels (even; portrait by default)."""
    height: int = 960
    """Frame height in pixels (even)."""
    force: bool = False
    """Write into a non-empty --out folder (files are overwritten one by one; nothing else is deleted)."""
    clean: bool = False
    """Skip the sensor model (noise, motion blur, exposure drift, vignetting): ideal frames, for debugging."""
    object_renders: bool = False
    """Also write objects/: the plant and the cube alone over black, without the sensor model, at the capture's base
    exposure: what an exact object-centric model would render (the trainer benchmark's ceiling)."""
    class_maps: bool = False
    """Also write classes/: the class id of the surface seen through each pixel centre (the masks' rule), so that
    mask errors can be told apart by organ and scene part (ids named in :data:`plantsplat.synth.mesh.CLASS_NAMES`)."""
    hard: bool = False
    """A harder capture, like many real ones: blank walls, the cube 5-15 cm from the pot and framed with the plant
    alone (its markers are seen in only part of the frames), twice the hand-held shake and larger exposure changes."""
    crf: int = 18
    """H.264 constant rate factor (lower = better quality, bigger file)."""
    msaa: int = 4
    """Multisample anti-aliasing samples for the colour pass (masks never use MSAA)."""
    gt_density: float = 20.0
    """Ground-truth surface samples per cm^2 in plant_gt.ply / scene_gt.ply (all mesh vertices are included too)."""

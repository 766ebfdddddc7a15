"""``plantsplat synth``: a synthetic phone capture of a potted strawberry plant with exact ground truth.

Example:
    >>> from pathlib import Path
    >>> from plantsplat.synth import SynthConfig, generate
    >>> info = generate(SynthConfig(seed=0, out=Path("/tmp/cap"), frames=36, width=180, height=320))  # doctest: +SKIP
    >>> info["paths"]["video"]                                                                       # doctest: +SKIP
    PosixPath('/tmp/cap/video.mp4')

Outputs (``OUT/``): ``video.mp4`` (H.264, 24 fps), ``frames/frame_00000.png`` (the same frames,
lossless), ``masks/frame_00000.png`` (255 = plant or cube), ``plant_gt.ply``, ``scene_gt.ply``, ``ground_truth.json`` and ``preview.png`` (six frames with their mask outlines). See :mod:`plantsplat.synth.capture`.
"""

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
    crf: int = 18
    """H.264 constant rate factor (lower = better quality, bigger file)."""
    msaa: int = 4
    """Multisample anti-aliasing samples for the colour pass (masks never use MSAA)."""
    gt_density: float = 20.0
    """Ground-truth surface samples per cm^2 in plant_gt.ply / scene_gt.ply (all mesh vertices are included too)."""


def generate(cfg: SynthConfig) -> dict:
    """Render the capture described by ``cfg``; returns ``{"paths": {...}, "timings": {...}, ...}``."""
    from plantsplat.synth.capture import generate as _generate

    return _generate(cfg)


__all__ = ["FORMAT", "SynthConfig", "generate"]

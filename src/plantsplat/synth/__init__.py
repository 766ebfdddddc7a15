"""``plantsplat synth``: a synthetic phone capture of a potted strawberry plant with exact ground truth.

Usage:
    from pathlib import Path
    from plantsplat.synth import SynthConfig, generate
    info = generate(SynthConfig(seed=0, out=Path("/tmp/cap"), frames=36, width=180, height=320))
    info["paths"]["video"]

Outputs (``OUT/``): ``video.mp4`` (H.264, 24 fps), ``frames/frame_00000.png`` (the same frames,
lossless), ``masks/frame_00000.png`` (255 = plant or cube), ``plant_gt.ply``, ``scene_gt.ply``, ``ground_truth.json``
and ``preview.png`` (six frames with their mask outlines). See :mod:`plantsplat.synth.capture`.
"""

from __future__ import annotations

from plantsplat.synth.config import FORMAT, SynthConfig


def generate(cfg: SynthConfig) -> dict:
    """Render the capture described by ``cfg`` (:func:`plantsplat.synth.capture.write_capture`); returns
    ``{"paths": {...}, "timings": {...}, ...}``."""
    from plantsplat.synth.capture import write_capture  # deferred: it loads moderngl, OpenCV and PyAV

    return write_capture(cfg)


__all__ = ["FORMAT", "SynthConfig", "generate"]

"""Object-centric 3D Gaussian Splatting: data, model, density control, training loop, metrics.

The stage's settings are :mod:`plantsplat.train.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.train.stage` (it loads torch, so it is imported when it runs). The trained model
is exported by its own stage, :mod:`plantsplat.export`.

Submodules: ``config`` (options, presets), ``data`` (cameras, frames, split, initial points),
``model`` (parameters), ``checkpoint`` (checkpoints, the finished model), ``render`` (rendering, image
cache), ``loss``, ``strategy`` (density control), ``trainer`` (the loop),
``evaluate`` and ``metrics`` (PSNR/SSIM/LPIPS), ``romi`` (ROMI importer).

Usage:
    from plantsplat.train import TrainConfig, stage
    summary = stage.run("ws/plant_01", TrainConfig(mode="object"))
"""

from plantsplat.train.config import TrainConfig

__all__ = ["TrainConfig"]

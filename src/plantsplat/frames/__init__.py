"""Frames: a video or image folder -> sharp, spread-out frames in a workspace's ``images/``.

The stage's settings are :mod:`plantsplat.frames.config`; the stage over a workspace (``run``, ``inputs``,
``outputs``) is :mod:`plantsplat.frames.stage`; the selection, :mod:`plantsplat.frames.select`; reading videos and
image folders, :mod:`plantsplat.frames.sources`.

Usage:
    from plantsplat.frames import FramesConfig, stage
    info = stage.run("ws/plant01", FramesConfig(num=120), "plant01.mp4")
"""

from plantsplat.frames.config import FramesConfig

__all__ = ["FramesConfig"]

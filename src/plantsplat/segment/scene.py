"""The quick whole-scene Gaussian model the segmenter decides the object in (trained once per capture).

It is an ordinary full-scene 3DGS model (plantsplat's own trainer, ``mode="full"``: no masks) at a low
resolution with few Gaussians: enough to put every surface of the room and the plant at its place in
3D. It lives in ``WS/.plantsplat/segment/scene/``; an interrupted segment stage resumes from its checkpoint.

Usage:
    params, views, points = scene_model(Workspace("ws/plant01"), SegmentConfig())
"""

from __future__ import annotations

from plantsplat.log import get_logger
from plantsplat.segment.config import SegmentConfig
from plantsplat.segment.stored import scene_dir
from plantsplat.train.checkpoint import load_model
from plantsplat.train.config import TrainConfig
from plantsplat.train.data import training_scene
from plantsplat.train.trainer import train_workspace
from plantsplat.workspace import Workspace

log = get_logger(__name__)

SCENE_TEST_FRACTION = 0.02
"""Share of the frames the quick model holds out of its training (it is never evaluated: as few as the split takes)."""


def scene_model(ws: Workspace, cfg: SegmentConfig, resume: bool = False):
    """Train the quick model (``resume``: from an interrupted run's checkpoint); returns ``(params, views,
    sfm points [P, 3])`` (tensors detached). Each view keeps its frame as decoded (``View.raw``): the frames are
    decoded once for the model and the masks."""
    out = scene_dir(ws)
    log.info("segment: a quick model of the whole scene (%d steps at %d px) to find the plant in 3D",
             cfg.scene_steps, cfg.scene_resolution)
    scene = training_scene(ws, "full", keep_raw=True)
    train_workspace(ws, TrainConfig(
        mode="full", backend="auto", preset="cpu", iterations=cfg.scene_steps, max_resolution=cfg.scene_resolution,
        num_downscales=0, sh_degree=1, max_gaussians=cfg.scene_max_gaussians, occluders=False, evaluate=False,
        test_fraction=SCENE_TEST_FRACTION, seed=cfg.seed, train_dir=out, metrics_path=out / "metrics.json"),
        resume=resume, scene=scene)
    params, _ = load_model(ws, out)
    return {k: v.detach().cpu() for k, v in params.items()}, scene.views, scene.points

"""SAM-2 backend: SAM-2's video predictor, prompted from the ``3d`` segmenter's masks, propagated over the frames.

The ``3d`` segmenter runs first; on key frames (every ``key_every``-th frame where it found the
object) the plant and the cube each get a box prompt (the bounding box of its mask) plus
positive points at the interior's most central pixels. SAM-2 then propagates both objects through
the whole frame sequence (its memory attention carries the masks between the prompts), and the
final foreground is the union of the two objects.

Uses only SAM-2's documented video API (``build_sam2_video_predictor``, ``init_state`` on a folder
of ``<index>.jpg`` frames, ``add_new_points_or_box``, ``propagate_in_video``). The video path of
the ``sam2`` package does not import torchvision, so it runs with the CPU build of torch.

Usage:
    masks, info = sam2_segment(paths, parts, Path("sam2.1_hiera_tiny.pt"),
                               "configs/sam2.1/sam2.1_hiera_t.yaml")
"""

from __future__ import annotations

import importlib.util
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.io import read_image
from plantsplat.log import get_logger, make_progress

log = get_logger(__name__)

MIN_PROMPT_PIXELS = 20
"""A mask smaller than this (pixels) gives no prompt."""
FRAME_JPEG_QUALITY = 95
"""JPEG quality of the frames written for SAM-2 (it reads a folder of JPEGs)."""
ERROR_CHARS = 160
"""SAM-2's own error is quoted up to this many characters."""
PIECE_CONNECTIVITY = 8
"""The pieces of a mask that prompts are placed in are 8-connected."""

INSTALL_HINT = (
    "SAM2_BUILD_CUDA=0 pip install -c constraints.txt --no-deps --no-build-isolation sam2==1.1.0 "
    "&& pip install -c constraints.txt hydra-core iopath tqdm pillow"
)
_SIZES = {"tiny": "t", "small": "s", "base_plus": "b+", "base-plus": "b+", "b+": "b+", "large": "l",
          "t": "t", "s": "s", "l": "l"}


def check_sam2(checkpoint: str | os.PathLike | None) -> Path:
    """Check that ``sam2`` is importable and the checkpoint file exists; return its path.

    Raises a one-line :class:`PlantsplatError` saying what to install or pass.
    """
    if importlib.util.find_spec("sam2") is None:
        raise PlantsplatError(f"the sam2 backend needs the `sam2` package; install it with: {INSTALL_HINT} "
                              "(or use --backend 3d)")
    if checkpoint is None:
        raise UsageError("--backend sam2 needs --sam2-checkpoint PATH (a SAM-2 checkpoint such as "
                         "sam2.1_hiera_tiny.pt from github.com/facebookresearch/sam2)")
    path = Path(checkpoint)
    if not path.is_file():
        raise PlantsplatError(f"{path}: SAM-2 checkpoint not found; download it (e.g. sam2.1_hiera_tiny.pt) "
                              "on a connected machine and pass its path to --sam2-checkpoint")
    return path


def resolve_config(checkpoint: Path, config: str | None) -> str:
    """The SAM-2 config name for a checkpoint: ``config`` when given, else guessed from the file name.

    Example:
        >>> resolve_config(Path("sam2.1_hiera_tiny.pt"), None)
        'configs/sam2.1/sam2.1_hiera_t.yaml'
    """
    if config:
        return config
    name = checkpoint.name.lower()
    m = re.search(r"(sam2(?:\.1)?)_hiera_(tiny|small|base_plus|base-plus|large|b\+|t|s|l)\b", name)
    if not m:
        raise UsageError(f"{checkpoint}: cannot tell the SAM-2 model from the file name; pass --sam2-config "
                         "(e.g. configs/sam2.1/sam2.1_hiera_t.yaml)")
    version, size = m.group(1), _SIZES[m.group(2)]
    return f"configs/{version}/{version}_hiera_{size}.yaml"


def random_checkpoint(config: str, path: str | os.PathLike, seed: int = 0) -> Path:
    """Save a SAM-2 checkpoint of the architecture ``config`` with random weights (``{'model': state_dict}``) to
    ``path``: for tests of the plumbing and for timing, never for masks (speed does not depend on the weights).

    Usage:
        random_checkpoint("configs/sam2.1/sam2.1_hiera_t.yaml", "/tmp/sam2.1_hiera_tiny.pt")
    """
    # deferred: SAM 2 and hydra, omegaconf (which come with it) are optional
    import sam2  # noqa: F401  (registers SAM-2's configs with hydra)
    from hydra import compose
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    cfg = compose(config_name=config)
    OmegaConf.resolve(cfg)
    torch.manual_seed(seed)
    torch.save({"model": instantiate(cfg.model, _recursive_=True).state_dict()}, path)
    return Path(path)


def _prompt(mask: np.ndarray, n_points: int = 3) -> tuple[np.ndarray, np.ndarray] | None:
    """Box ``[4]`` (x0, y0, x1, y1) and positive points ``[n, 2]`` (x, y) from a bool mask ``[H, W]``."""
    ys, xs = np.nonzero(mask)
    if len(xs) < MIN_PROMPT_PIXELS:
        return None
    box = np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float32)
    # points: the most interior pixels of the largest pieces (distance-transform maxima)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=PIECE_CONNECTIVITY)
    order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA])
    pts = []
    for k in order[:n_points]:
        dt = cv2.distanceTransform((lab == k).astype(np.uint8), cv2.DIST_L2, 3)
        y, x = np.unravel_index(int(np.argmax(dt)), dt.shape)
        pts.append((x, y))
    return box, np.array(pts, np.float32)


def sam2_segment(
    image_paths: list[Path],
    parts: list[tuple[np.ndarray, np.ndarray]],
    checkpoint: Path,
    config: str,
    device: str | None = None,
    key_every: int = 10,
    image_size: int | None = None,
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Run SAM-2's video predictor over the frames, prompted from the ``3d`` segmenter's ``(plant, cube)`` masks.

    ``image_size`` overrides the model's input size (SAM-2 is trained at 1024; smaller sizes only
    make sense for tests of the plumbing). Returns per-frame bool masks ``[H, W]`` (plant or cube)
    and facts for ``segment.json``.
    """
    from sam2.build_sam import build_sam2_video_predictor  # deferred: SAM 2 is optional

    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    n = len(image_paths)
    if device == "cpu":
        log.warning("segment: SAM-2 runs on the CPU, which is slow (the tiny model took about 17 s per frame on 2 "
                    "cores in benchmarks/bench_segment.py, so 120 frames take over half an hour); the 3d backend "
                    "takes under a second")
    try:
        extra = [f"++model.image_size={int(image_size)}"] if image_size else []
        predictor = build_sam2_video_predictor(config, str(checkpoint), device=device, hydra_overrides_extra=extra)
    except Exception as exc:  # wrong config for the weights, corrupt file, ...
        raise PlantsplatError(f"{checkpoint}: SAM-2 could not load it with config {config} "
                              f"({type(exc).__name__}: {str(exc).splitlines()[0][:ERROR_CHARS] if str(exc) else ''}); "
                              "check --sam2-config matches the checkpoint") from exc
    H = W = None
    with tempfile.TemporaryDirectory(prefix="plantsplat_sam2_") as tmp:
        for i, p in enumerate(image_paths):  # SAM-2 reads a folder of <index>.jpg frames
            rgb = read_image(p)
            H, W = rgb.shape[:2]
            cv2.imwrite(os.path.join(tmp, f"{i:05d}.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_JPEG_QUALITY, FRAME_JPEG_QUALITY])
        out = [np.zeros((H, W), bool) for _ in range(n)]
        prompts = 0
        with torch.inference_mode():
            state = predictor.init_state(video_path=tmp, offload_video_to_cpu=True, offload_state_to_cpu=device == "cpu")
            keys = list(range(0, n, max(1, key_every)))
            for obj_id, part in ((1, 0), (2, 1)):
                for k in keys:
                    pr = _prompt(parts[k][part])
                    if pr is None:
                        continue
                    box, pts = pr
                    predictor.add_new_points_or_box(state, frame_idx=k, obj_id=obj_id, points=pts,
                                                    labels=np.ones(len(pts), np.int32), box=box)
                    prompts += 1
            if prompts == 0:
                raise PlantsplatError(f"{image_paths[0].parent}: the 3d segmenter found nothing to prompt "
                                      "SAM-2 with; check the capture")
            with make_progress() as bar:
                task = bar.add_task("segment: SAM-2 propagation", total=n, info="")
                for frame_idx, _obj_ids, logits in predictor.propagate_in_video(state):
                    out[frame_idx] = (logits > 0.0).any(dim=0).reshape(H, W).cpu().numpy()
                    bar.advance(task)
                first = min(k for k in keys)
                if first > 0:  # frames before the first prompt
                    for frame_idx, _obj_ids, logits in predictor.propagate_in_video(state, start_frame_idx=first,
                                                                                    reverse=True):
                        out[frame_idx] = (logits > 0.0).any(dim=0).reshape(H, W).cpu().numpy()
    return out, {"key_every": key_every, "prompts": prompts, "device": device, "image_size": image_size or "model default"}

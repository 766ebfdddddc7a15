"""Image metrics of a trained model on the stored test views -> ``metrics.json``.

Three comparisons per test view, all at the training's final resolution and over a fixed black
background ``B``:

- ``composite``: the whole frame. Object mode: render over ``B`` against the frame composited over
  ``B`` through its mask (the object is all the model is asked to explain). Full mode: render
  against the raw frame.
- ``foreground``: PSNR and SSIM averaged over the mask's pixels only; LPIPS on the mask's bounding
  box with both images composited over ``B`` through the mask. ``psnr_interior``: PSNR over the mask
  without its 2 px outline (:func:`~plantsplat.train.metrics.mask_interior`). A frame's outline pixels
  mix the object with the room behind it, which no object model renders, and they carry much of the
  foreground's error (on seed 0 of the training benchmark an exact render of the plant and cube alone scores
  about 6 dB less there than inside).
- ``pbr`` (full mode with masks, the post-background-removal baseline): the full model's render
  with the test frame's own mask applied after training, against the frame composited over ``B``.
  The mask is the frame's, so the render is clipped exactly where the target is: an upper bound.
- ``pbr_segmented`` (full mode with masks): the paper's PBR as the paper ran it. The paper removes
  the background from the *renders* with SAM-2; here the renders of the test views are segmented
  as the segment stage cut the frames (its 3D object drawn into each test camera, refined on the
  render), each render is clipped by its own mask and scored against the frame
  composited over ``B`` as above (the render as the 8-bit image the segmenter sees). ``mask_iou``
  compares those masks with the test frames' masks. A render in which the segmenter finds nothing is
  scored as all background; None, with ``pbr_segmented_error``, where the segmenter fails outright.

Usage:
    m = evaluate_workspace(Workspace("ws/plant_01"))
    m["composite"]["psnr"]
"""

from __future__ import annotations

import resource
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from plantsplat.errors import PlantsplatError
from plantsplat.io import write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, progress
from plantsplat.raster import resolve_backend
from plantsplat.resources import usable_cores
from plantsplat.segment.scores import mask_iou
from plantsplat.segment.stored import segment_images
from plantsplat.train import data as D
from plantsplat.train.checkpoint import load_model
from plantsplat.train.metrics import load_lpips, lpips, mask_interior, masked_mean, psnr, scored_ssim_map
from plantsplat.train.model import sh_degree_of
from plantsplat.train.render import ImageCache, occluders_from, render
from plantsplat.workspace import Workspace

log = get_logger(__name__)


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else None


@dataclass
class _Evaluation:
    """What scoring a test view needs: the model on its device, the views and their images, LPIPS."""

    params: object
    views: dict
    cache: object
    net: object
    sh: int
    backend: str
    device: torch.device
    object_mode: bool
    occ: object
    bg: torch.Tensor


def _render_view(ev: _Evaluation, name: str, fps_repeats: int):
    """Render test view ``name`` over the background. Returns ``(pred, img, alpha, viewmat, K, w, h, seconds)``."""
    img, alpha, K, w, h = ev.cache.get(name, 1)
    viewmat = torch.tensor(ev.views[name].viewmat, dtype=torch.float32, device=ev.device)
    t0 = time.perf_counter()
    for _ in range(fps_repeats):
        out = render(ev.params, viewmat, K, w, h, ev.sh, ev.backend, ev.occ, ev.bg.to(ev.device))
    if ev.device.type == "cuda":
        torch.cuda.synchronize()
    seconds = (time.perf_counter() - t0) / fps_repeats
    color, out_alpha = out.color.cpu(), out.alpha.cpu()
    img, alpha = img.cpu(), None if alpha is None else alpha.cpu()
    pred = (color + (1 - out_alpha) * ev.bg).clamp(0, 1)  # [h, w, 3]
    return pred, img, alpha, viewmat, K, w, h, seconds


def _score_view(ev: _Evaluation, name: str, pred, img, alpha, viewmat, K, w, h, save_dir: Path | None) -> dict:
    """One test view's row: composite, foreground and (full mode) PBR scores; its render saved to ``save_dir``."""
    bg = ev.bg
    row = {"name": name}
    gt_fg = img * alpha + (1 - alpha) * bg if alpha is not None else None  # [h, w, 3]
    gt = gt_fg if (ev.object_mode and gt_fg is not None) else img
    if ev.object_mode and alpha is not None:
        row["mask_agreement"] = mask_agreement(render(ev.params, viewmat, K, w, h, 0, ev.backend).alpha.cpu(), alpha)
    if save_dir is not None:
        stem = Path(name).stem
        write_image_atomic(save_dir / f"{stem}_render.png", _to_u8(pred))
        write_image_atomic(save_dir / f"{stem}_gt.png", _to_u8(gt))
    smap = scored_ssim_map(pred, gt)  # [h, w, 3]; object mode: the foreground's SSIM is its mean over the mask
    row["composite"] = {"psnr": float(psnr(pred, gt)), "ssim": float(smap.mean()), "lpips": lpips(ev.net, pred, gt)}
    if alpha is not None and float(alpha.sum()) > 0:
        pred_m = pred * alpha + (1 - alpha) * bg
        x0, y0, x1, y1 = _box(alpha)
        row["foreground"] = foreground_scores(pred, gt_fg, alpha, smap if gt is gt_fg else None)
        row["foreground"]["lpips"] = lpips(ev.net, pred_m[y0:y1, x0:x1], gt_fg[y0:y1, x0:x1])
        if not ev.object_mode:
            row["pbr"] = {"psnr": float(psnr(pred_m, gt_fg)), "ssim": float(scored_ssim_map(pred_m, gt_fg).mean()),
                          "lpips": lpips(ev.net, pred_m, gt_fg)}
    return row


def _score_segmented_pbr(ws: Workspace, ev: _Evaluation, per_view: list[dict], pbr_renders: dict) -> str | None:
    """The paper's PBR: each test render segmented as the frames were, clipped by its own mask and scored.
    Adds ``pbr_segmented`` to the rows; returns the segmenter's error, if any."""
    seg_masks, error = segment_renders(ws, pbr_renders)
    bg = ev.bg
    for row in per_view if seg_masks else ():
        img, alpha = (t.cpu() for t in ev.cache.get(row["name"], 1)[:2])
        gt_fg = img * alpha + (1 - alpha) * bg
        m = torch.from_numpy(seg_masks[row["name"]]).float()[..., None]  # [h, w, 1] in {0, 1}
        pred = torch.from_numpy(pbr_renders[row["name"]]).float() / 255.0
        pred_m = pred * m + (1 - m) * bg
        row["pbr_segmented"] = {"psnr": float(psnr(pred_m, gt_fg)), "ssim": float(scored_ssim_map(pred_m, gt_fg).mean()),
                                "lpips": lpips(ev.net, pred_m, gt_fg), "mask_iou": mask_iou(alpha > 0.5, m > 0.5)}
    return error


_AGGREGATED = ("psnr", "ssim", "lpips", "psnr_interior", "mask_iou", "iou", "mask_rendered", "render_in_mask")


def _aggregate(per_view: list[dict], kind: str) -> dict | None:
    rows = [r[kind] for r in per_view if kind in r]
    if not rows:
        return None
    return {k: _mean([r.get(k) for r in rows]) for k in _AGGREGATED if any(k in r for r in rows)}


def _saved_views(names: list[str]) -> set[str]:
    """A few test views, evenly spaced, saved next to their ground truth for the report."""
    n_saved = min(8, len(names))
    return {names[int(round(i * (len(names) - 1) / max(1, n_saved - 1)))] for i in range(n_saved)}


def _evaluation(ws: Workspace, train_dir, lpips_weights, backend: str, scene):
    """The model, its test views and what scoring them needs. Returns ``(ev, names, cfg, split, scene, scale)``."""
    params, extra = load_model(ws, train_dir)
    cfg, split = extra["config"], extra["split"]
    backend = resolve_backend(backend)
    if not split["test"]:
        log.warning("no test views in the split; metrics are computed on the training views")
    names = split["test"] or split["train"]
    if scene is None:
        scene = D.load_scene(ws, need_masks=False)
    views = {v.name: v for v in scene.views}
    missing = [n for n in names if n not in views]
    if missing:
        raise PlantsplatError(f"{ws.root}: test frame {missing[0]} has no pose or image any more; retrain with --force")
    max_side = max(max(v.width, v.height) for v in scene.views)
    base_scale = min(1.0, cfg["max_resolution"] / max_side) if cfg["max_resolution"] else 1.0
    device = torch.device("cuda" if backend == "gsplat" else "cpu")
    params = params.to(device)
    object_mode = cfg["mode"] == "object"
    ev = _Evaluation(
        params=params, views=views, cache=ImageCache([views[n] for n in names], base_scale, device),
        net=load_lpips(lpips_weights), sh=sh_degree_of(params), backend=backend, device=device,
        object_mode=object_mode, bg=torch.zeros(3),
        occ=occluders_from(extra.get("occluders"), device) if object_mode else None,  # drawn in bg, as in training
    )
    return ev, names, cfg, split, scene, base_scale


def evaluate_workspace(ws: Workspace, train_dir: Path | None = None, metrics_path: Path | None = None,
                       lpips_weights: Path | None = None, backend: str = "auto", train_summary: dict | None = None,
                       scene: D.Scene | None = None, fps_repeats: int = 1) -> dict:
    """Evaluate the finished model of ``ws`` on its test views and write ``metrics.json``."""
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    ev, names, cfg, split, scene, base_scale = _evaluation(ws, train_dir, lpips_weights, backend, scene)
    per_view = []
    pbr_renders: dict[str, np.ndarray] = {}  # full mode: test renders (uint8) for the segmented PBR
    render_seconds = 0.0
    n_px = 0
    renders_dir = Path(train_dir or ws.train_dir) / "renders"
    saved = _saved_views(names)
    with torch.no_grad(), scoring_threads():
        for name in progress(names, "evaluating test views"):
            pred, img, alpha, viewmat, K, w, h, seconds = _render_view(ev, name, fps_repeats)
            render_seconds += seconds
            n_px = w * h
            row = _score_view(ev, name, pred, img, alpha, viewmat, K, w, h, renders_dir if name in saved else None)
            if "pbr" in row:
                pbr_renders[name] = _to_u8(pred)
            per_view.append(row)
    pbr_segmented_error = _score_segmented_pbr(ws, ev, per_view, pbr_renders) if pbr_renders else None

    summary = dict(train_summary or {})
    summary.pop("metrics", None)
    metrics = {
        "mode": cfg["mode"],
        "backend": ev.backend,
        "n_test_views": len(names),
        "split": split.get("method"),
        "resolution": [int(round(scene.views[0].width * base_scale)), int(round(scene.views[0].height * base_scale))],
        "background": ev.bg.tolist(),
        "composite": _aggregate(per_view, "composite"),
        "foreground": _aggregate(per_view, "foreground"),
        "pbr": _aggregate(per_view, "pbr"),
        "pbr_segmented": _aggregate(per_view, "pbr_segmented"),
        "pbr_segmented_error": pbr_segmented_error,
        "mask_agreement": _aggregate(per_view, "mask_agreement"),
        "lpips_weights": None if ev.net is None else "loaded",
        "n_gaussians": int(ev.params["means"].shape[0]),
        "render_fps": len(names) / render_seconds if render_seconds > 0 else None,
        "render_megapixels": n_px / 1e6,
        "train_seconds": summary.get("train_seconds"),
        "train_cpu_seconds": summary.get("train_cpu_seconds"),
        "iterations": cfg["iterations"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "per_view": per_view,
    }
    if torch.cuda.is_available():
        metrics["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20
    if metrics_path is None:
        metrics_path = ws.metrics_json
    write_json_atomic(metrics_path, metrics)
    _log_metrics(metrics, metrics_path)
    return metrics


@contextmanager
def scoring_threads():
    """Torch on every core this process may use (:func:`plantsplat.resources.usable_cores`) while the test views are
    scored: training leaves torch on one thread (``TrainConfig.threads``), and LPIPS's and SSIM's convolutions over
    whole frames are the evaluation's main cost."""
    before = torch.get_num_threads()
    torch.set_num_threads(usable_cores())
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _log_metrics(metrics: dict, metrics_path: Path) -> None:
    c = metrics["composite"]
    f = metrics["foreground"] or {}
    log.info("test views: PSNR %.2f SSIM %.4f LPIPS %s | foreground PSNR %s SSIM %s | %.2f FPS -> %s",
             c["psnr"], c["ssim"], _fmt(c["lpips"]), _fmt(f.get("psnr")), _fmt(f.get("ssim")),
             metrics["render_fps"] or 0, metrics_path)
    for key, label in (("pbr", "test frames' masks"), ("pbr_segmented", "renders segmented")):
        if metrics[key]:
            log.info("PBR (%s): PSNR %.2f SSIM %.4f LPIPS %s", label, metrics[key]["psnr"], metrics[key]["ssim"],
                     _fmt(metrics[key]["lpips"]))


def mask_agreement(model_alpha: torch.Tensor, mask: torch.Tensor) -> dict:
    """How a trained object model and a test frame's mask agree (``[h, w]`` or ``[h, w, 1]`` in [0, 1], cut at 0.5):
    ``iou``, ``mask_rendered`` (the share of the mask the model draws) and ``render_in_mask`` (the share of what
    the model draws that the mask holds). A mask that takes room or leaves out plant tissue the other views show
    is not drawn by a model that has to agree with every view."""
    a, m = model_alpha.reshape(mask.shape[:2]) > 0.5, mask.reshape(mask.shape[:2]) > 0.5
    both = float((a & m).sum())
    return {"iou": mask_iou(a, m), "mask_rendered": both / max(float(m.sum()), 1.0),
            "render_in_mask": both / max(float(a.sum()), 1.0)}


def segment_renders(ws: Workspace, renders: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray] | None, str | None]:
    """Segment a full model's renders ``{name: [h, w, 3] uint8 RGB}`` as the workspace's frames were segmented: the
    segment stage's 3D object drawn into each test camera and refined on the render
    (:func:`plantsplat.segment.stored.segment_images`). Returns ``({name: [h, w] bool mask}, None)``, or
    ``(None, reason)`` when the workspace has no such object (masks imported, or not segmented here)."""
    log.info("PBR: segmenting %d test renders of the full model, as the paper removes the background after training",
             len(renders))
    try:
        return segment_images(ws, renders), None
    except PlantsplatError as e:
        log.warning("PBR: the renders could not be segmented (%s); pbr_segmented is left out", e)
        return None, str(e)


def foreground_scores(pred: torch.Tensor, gt_fg: torch.Tensor, alpha: torch.Tensor,
                      smap: torch.Tensor | None = None) -> dict:
    """PSNR and SSIM of a render ``pred`` ``[h, w, 3]`` against the frame composited through its mask ``gt_fg`` over
    the mask ``alpha`` ``[h, w, 1]``, and the PSNR over the mask's interior (None when the mask has none).
    ``smap``: the SSIM map of ``pred`` against ``gt_fg`` when the caller has it already."""
    inner = mask_interior(alpha)
    smap = scored_ssim_map(pred, gt_fg) if smap is None else smap
    return {"psnr": float(psnr(pred, gt_fg, alpha)), "ssim": float(masked_mean(smap, alpha)),
            "psnr_interior": float(psnr(pred, gt_fg, inner)) if float(inner.sum()) > 0 else None}


def _to_u8(img: torch.Tensor):
    """[h, w, 3] float in [0, 1] -> uint8 numpy."""
    return (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


def _fmt(x):
    return "n/a" if x is None else f"{x:.4f}"


def _box(alpha: torch.Tensor) -> tuple[int, int, int, int]:
    ys, xs = torch.nonzero(alpha[..., 0] > 0.01, as_tuple=True)
    x0, x1 = int(xs.min()), int(xs.max()) + 1
    y0, y1 = int(ys.min()), int(ys.max()) + 1
    # LPIPS needs at least ~32 px on a side (AlexNet's strides)
    h, w = alpha.shape[:2]
    if x1 - x0 < 32:
        x0, x1 = max(0, min(x0, w - 32)), min(w, max(x1, x0 + 32))
    if y1 - y0 < 32:
        y0, y1 = max(0, min(y0, h - 32)), min(h, max(y1, y0 + 32))
    return x0, y0, x1, y1

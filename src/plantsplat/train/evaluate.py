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
- ``pbr`` (full mode with masks, the paper's post-background-removal baseline): the full model's
  render with the mask applied after training, against the frame composited over ``B``.

Example:
    >>> m = evaluate_workspace(Workspace("ws/plant_01"))  # doctest: +SKIP
    >>> m["composite"]["psnr"]  # doctest: +SKIP
    31.2
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np
import torch

from plantsplat.errors import PlantsplatError
from plantsplat.io import write_image_atomic, write_json_atomic
from plantsplat.log import get_logger, progress
from plantsplat.train import data as D
from plantsplat.train.metrics import load_lpips, lpips, mask_interior, psnr, ssim
from plantsplat.train.model import sh_degree_of
from plantsplat.workspace import Workspace

log = get_logger(__name__)


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else None


def evaluate_workspace(ws: Workspace, train_dir: Path | None = None, metrics_path: Path | None = None,
                       lpips_weights: Path | None = None, backend: str = "auto", train_summary: dict | None = None,
                       scene: D.Scene | None = None, fps_repeats: int = 1) -> dict:
    """Evaluate the finished model of ``ws`` on its test views and write ``metrics.json``."""
    from plantsplat.raster import resolve_backend
    from plantsplat.train.trainer import ImageCache, _occluders_from, load_model, render

    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    params, extra = load_model(ws, train_dir)
    cfg = extra["config"]
    split = extra["split"]
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
    cache = ImageCache([views[n] for n in names], base_scale, device)
    net = load_lpips(lpips_weights)
    sh = sh_degree_of(params)
    object_mode = cfg["mode"] == "object"
    bg = torch.zeros(3)
    occ = _occluders_from(extra.get("occluders"), device) if object_mode else None  # drawn in bg, as in training
    per_view = []
    render_seconds = 0.0
    n_px = 0
    # a few test views, evenly spaced, are saved next to their ground truth for the report
    renders_dir = Path(train_dir or ws.train_dir) / "renders"
    n_saved = min(8, len(names))
    saved = {names[int(round(i * (len(names) - 1) / max(1, n_saved - 1)))] for i in range(n_saved)}
    with torch.no_grad():
        for name in progress(names, "evaluating test views"):
            img, alpha, K, w, h = cache.get(name, 1)
            viewmat = torch.tensor(views[name].viewmat, dtype=torch.float32, device=device)
            t0 = time.perf_counter()
            for _ in range(fps_repeats):
                out = render(params, viewmat, K, w, h, sh, backend, occ, bg.to(device))
            if device.type == "cuda":
                torch.cuda.synchronize()
            render_seconds += (time.perf_counter() - t0) / fps_repeats
            out.color, out.alpha = out.color.cpu(), out.alpha.cpu()
            img, alpha = img.cpu(), None if alpha is None else alpha.cpu()
            n_px = w * h
            pred = (out.color + (1 - out.alpha) * bg).clamp(0, 1)  # [h, w, 3]
            row = {"name": name}
            if alpha is not None:
                gt_fg = img * alpha + (1 - alpha) * bg  # [h, w, 3]
            else:
                gt_fg = None
            gt = gt_fg if (object_mode and gt_fg is not None) else img
            if name in saved:
                stem = Path(name).stem
                write_image_atomic(renders_dir / f"{stem}_render.png", _to_u8(pred))
                write_image_atomic(renders_dir / f"{stem}_gt.png", _to_u8(gt))
            row["composite"] = {"psnr": float(psnr(pred, gt)), "ssim": float(ssim(pred, gt)),
                                "lpips": lpips(net, pred, gt)}
            if alpha is not None and float(alpha.sum()) > 0:
                pred_m = pred * alpha + (1 - alpha) * bg
                x0, y0, x1, y1 = _box(alpha)
                row["foreground"] = foreground_scores(pred, gt_fg, alpha)
                row["foreground"]["lpips"] = lpips(net, pred_m[y0:y1, x0:x1], gt_fg[y0:y1, x0:x1])
                if not object_mode:
                    row["pbr"] = {"psnr": float(psnr(pred_m, gt_fg)), "ssim": float(ssim(pred_m, gt_fg)),
                                  "lpips": lpips(net, pred_m, gt_fg)}
            per_view.append(row)

    def agg(kind):
        rows = [r[kind] for r in per_view if kind in r]
        if not rows:
            return None
        return {k: _mean([r.get(k) for r in rows]) for k in ("psnr", "ssim", "lpips", "psnr_interior")
                if any(k in r for r in rows)}

    summary = dict(train_summary or {})
    summary.pop("metrics", None)
    metrics = {
        "mode": cfg["mode"],
        "backend": backend,
        "n_test_views": len(names),
        "split": split.get("method"),
        "resolution": [int(round(scene.views[0].width * base_scale)), int(round(scene.views[0].height * base_scale))],
        "background": bg.tolist(),
        "composite": agg("composite"),
        "foreground": agg("foreground"),
        "pbr": agg("pbr"),
        "lpips_weights": None if net is None else "loaded",
        "n_gaussians": int(params["means"].shape[0]),
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
    c = metrics["composite"]
    f = metrics["foreground"] or {}
    log.info("test views: PSNR %.2f SSIM %.4f LPIPS %s | foreground PSNR %s SSIM %s | %.2f FPS -> %s",
             c["psnr"], c["ssim"], _fmt(c["lpips"]), _fmt(f.get("psnr")), _fmt(f.get("ssim")),
             metrics["render_fps"] or 0, metrics_path)
    return metrics


def foreground_scores(pred: torch.Tensor, gt_fg: torch.Tensor, alpha: torch.Tensor) -> dict:
    """PSNR and SSIM of a render ``pred`` ``[h, w, 3]`` against the frame composited through its mask ``gt_fg`` over
    the mask ``alpha`` ``[h, w, 1]``, and the PSNR over the mask's interior (None when the mask has none)."""
    inner = mask_interior(alpha)
    return {"psnr": float(psnr(pred, gt_fg, alpha)), "ssim": float(ssim(pred, gt_fg, alpha)),
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

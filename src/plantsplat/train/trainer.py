"""The training loop: object-centric (RGBA, random background) or full-frame 3DGS, resumable.

Object mode (the paper, section 2.3): every step renders a training view, composites it over a
random colour ``B`` (``C_hat = C_splat + (1 - alpha_acc) * B``) and compares it with the frame
composited over the same ``B`` through its mask (``C = alpha_img * I + (1 - alpha_img) * B``), with
``(1 - 0.2) * L1 + 0.2 * (1 - SSIM)``. Outside the mask the target is ``B`` itself, which changes
every step, so the only way to match it is transparency: Gaussians there lose opacity and are
culled below 0.1. Full mode is plain RGB 3DGS on whole frames (the paper's Splatfacto baseline);
PBR is the full model evaluated with the masks applied after training (see :mod:`.evaluate`).

Example:
    >>> from plantsplat.workspace import Workspace
    >>> summary = train_workspace(Workspace("ws/plant_01"), TrainConfig(iterations=500))  # doctest: +SKIP
    >>> summary["n_gaussians"]  # doctest: +SKIP
    41210
"""

from __future__ import annotations

import os
import time
from types import SimpleNamespace
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

import plantsplat
from plantsplat.errors import PlantsplatError
from plantsplat.io import write_json_atomic
from plantsplat.log import get_logger, make_progress
from plantsplat.train import data as D
from plantsplat.train.metrics import ssim as ssim_torch
from plantsplat.train.model import (
    activated,
    init_params,
    load_checkpoint,
    make_optimizers,
    params_from_checkpoint,
    save_checkpoint,
)
from plantsplat.train.strategy import DensityStrategy
from plantsplat.workspace import Workspace

log = get_logger(__name__)

from plantsplat.train.config import PRESETS, ResolvedConfig, TrainConfig  # noqa: E402,F401


# ---------------------------------------------------------------------------------------------
# images at several resolutions


class ImageCache:
    """Per view, per downscale factor: image ``[h, w, 3]`` and alpha ``[h, w, 1]`` float tensors."""

    def __init__(self, views: list[D.View], base_scale: float, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.views = {v.name: v for v in views}
        self.base_scale = base_scale  # full resolution -> largest training resolution
        self._cache: dict[tuple[str, int], tuple] = {}
        self._boxes: dict[tuple[str, int], tuple[int, int, int, int]] = {}

    def box(self, name: str, down: int) -> tuple[int, int, int, int]:
        """:func:`foreground_box` of a view's alpha at one downscale (computed once)."""
        key = (name, down)
        if key not in self._boxes:
            img, alpha = self.get(name, down)[:2]
            self._boxes[key] = foreground_box(alpha) if alpha is not None else (0, 0, img.shape[1], img.shape[0])
        return self._boxes[key]

    def get(self, name: str, down: int):
        import cv2

        key = (name, down)
        if key not in self._cache:
            v = self.views[name]
            s = self.base_scale / down
            w, h = max(1, round(v.width * s)), max(1, round(v.height * s))
            interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
            img = cv2.resize(v.image, (w, h), interpolation=interp) if (w, h) != (v.width, v.height) else v.image
            img_t = torch.from_numpy(np.ascontiguousarray(img)).float() / 255.0  # [h, w, 3]
            if v.mask is not None:
                m = cv2.resize(v.mask, (w, h), interpolation=interp) if (w, h) != (v.width, v.height) else v.mask
                a_t = torch.from_numpy(np.ascontiguousarray(m)).float()[..., None] / 255.0  # [h, w, 1]
            else:
                a_t = None
            K = v.K.copy()
            K[0, :] *= w / v.width
            K[1, :] *= h / v.height
            dev = self.device
            self._cache[key] = (img_t.to(dev), None if a_t is None else a_t.to(dev),
                                torch.tensor(K, dtype=torch.float32, device=dev), w, h)
        return self._cache[key]


def foreground_box(alpha: torch.Tensor, margin_frac: float = 0.08, min_margin: int = 8) -> tuple[int, int, int, int]:
    """Bounding box ``(x0, y0, x1, y1)`` of ``alpha > 0`` ``[h, w, 1]`` grown by a margin; the whole
    image when the mask is empty."""
    h, w = alpha.shape[:2]
    ys, xs = torch.nonzero(alpha[..., 0] > 0.01, as_tuple=True)
    if len(xs) == 0:
        return 0, 0, w, h
    mx = max(min_margin, int(margin_frac * w))
    my = max(min_margin, int(margin_frac * h))
    x0, x1 = max(0, int(xs.min()) - mx), min(w, int(xs.max()) + 1 + mx)
    y0, y1 = max(0, int(ys.min()) - my), min(h, int(ys.max()) + 1 + my)
    return x0, y0, x1, y1


def photometric_loss(color: torch.Tensor, alpha: torch.Tensor, bg: torch.Tensor, gt: torch.Tensor,
                     ssim_lambda: float, gt_alpha: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The training loss of a render (``color`` ``[H, W, 3]``, ``alpha`` ``[H, W, 1]``) composited
    over ``bg`` ``[3]``: ``(1 - l) L1 + l (1 - SSIM)`` against ``gt``, and the mean squared error
    (detached, for the progress bar's PSNR). With ``gt_alpha`` (object mode) the target is ``gt``
    composited over the same background through it, ``gt gt_alpha + (1 - gt_alpha) bg``.

    On the CPU: the fused numba kernels of :mod:`plantsplat.raster.ssim` (compositing, L1, SSIM and
    their gradients in two passes; same value and gradients as the PyTorch composition, tested). The
    PyTorch version took about half of a training step at 896 px, and its elementwise operations
    alone a fifth. Elsewhere (CUDA, or a ``gt`` or ``bg`` that needs a gradient, which the fused
    kernels do not give): the PyTorch composition with :func:`plantsplat.train.metrics.ssim`.
    """
    if (color.device.type == "cpu" and gt.device.type == "cpu" and not gt.requires_grad and not bg.requires_grad
            and color.shape[-1] == 3 and (gt_alpha is None or not gt_alpha.requires_grad)):
        from plantsplat.raster.ssim import photometric_loss_cpu

        return photometric_loss_cpu(color, alpha, bg, gt, ssim_lambda, gt_alpha)
    if gt_alpha is not None:
        gt = gt * gt_alpha + (1.0 - gt_alpha) * bg
    pred = color + (1.0 - alpha) * bg
    loss = (1 - ssim_lambda) * (pred - gt).abs().mean() + ssim_lambda * (1 - ssim_torch(pred, gt))
    return loss, ((pred.detach() - gt.detach()) ** 2).mean()


# Occluders start opaque and at half the model's initial size (half the mean distance to their 3 nearest
# SfM neighbours): they stand for solid pot and soil. Pixels the plant leaves partly transparent go on
# through the occluders behind it, and wide, half-transparent occluders made every such pixel composite
# many of them: at 0.5 opacity and full size they added 75 % to the composited pairs, at 0.99 and half
# size 47 % (my script, seed 0 of the training benchmark: 2000 steps 169 s -> 153 s, whole-frame and
# foreground PSNR within 0.1 dB).
_OCC_OPACITY = 0.99
_OCC_SCALE = 0.5


def render(params, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, sh_degree: int, backend: str,
           occluders=None, bg: torch.Tensor | None = None):
    """Rasterize the model's Gaussians (activating the parameters) into one view.

    ``occluders`` (object mode; means, scales, quats, opacities like ``params``) are drawn after the
    model's Gaussians in the list, in the background colour ``bg`` ``[3]``: composited over ``bg``
    they look like background, but hide what lies behind them. The result's per-Gaussian outputs
    (``means2d``, ``radii``) then cover the model's Gaussians first, the occluders after them. With
    occluders, use the result only composited over ``bg``: the cpu backend drops occluders with nothing
    of the model behind them (``trailing_background``), which leaves that composite and every gradient
    as they were but not ``alpha`` alone.
    """
    from plantsplat.raster import rasterize
    from plantsplat.train.model import rgb_to_sh

    k = (sh_degree + 1) ** 2
    colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], dim=1)  # [N, k, 3]
    means, quats, scales, opac = params["means"], params["quats"], params["scales"], params["opacities"]
    m = 0
    if occluders is not None and occluders["means"].shape[0]:
        m = occluders["means"].shape[0]
        occ_col = torch.zeros(m, k, 3, device=colors.device, dtype=colors.dtype)
        occ_col[:, 0] = rgb_to_sh(bg.to(colors.dtype))  # colour = 0.5 + C0 sh0 = bg; higher bands 0
        colors = torch.cat([colors, occ_col])
        means = torch.cat([means, occluders["means"]])
        quats = torch.cat([quats, occluders["quats"]])
        scales = torch.cat([scales, occluders["scales"]])
        opac = torch.cat([opac, occluders["opacities"]])
    # occluders with nothing of the model behind them change neither the composite over bg nor a gradient
    return rasterize(means, quats, torch.exp(scales), torch.sigmoid(opac), colors, viewmat, K, width, height,
                     sh_degree=sh_degree, backend=backend, trailing_background=m)


class _ModelPart:
    """What the density strategy reads after backward (``radii``, ``means2d.grad``) for the model's own
    Gaussians: the first ``n`` of a render that also drew occluders."""

    def __init__(self, out, n: int):
        self.radii = out.radii[:n]
        grad = out.means2d.grad
        self.means2d = SimpleNamespace(grad=None if grad is None else grad[:n])


def scene_scale(views: list[D.View]) -> float:
    """1.1 x the largest distance of a camera centre from their mean (as gsplat's trainer)."""
    c = np.stack([v.center for v in views])
    return float(np.linalg.norm(c - c.mean(0), axis=1).max() * 1.1) or 1.0


# ---------------------------------------------------------------------------------------------
# the loop


def _paths(ws: Workspace, cfg: TrainConfig) -> dict[str, Path]:
    tdir = Path(cfg.train_dir) if cfg.train_dir else ws.train_dir
    return {
        "dir": tdir,
        "split": tdir / "split.json",
        "ckpt": tdir / "checkpoint.pt",
        "model": tdir / "model.pt",
        "config": tdir / "config.json",
        "metrics": Path(cfg.metrics_path) if cfg.metrics_path else ws.metrics_json,
    }


def model_path(ws: Workspace, train_dir: Path | None = None) -> Path:
    return (Path(train_dir) if train_dir else ws.train_dir) / "model.pt"


def train_workspace(ws: Workspace | str | os.PathLike, cfg: TrainConfig | None = None) -> dict:
    """Train (or resume, or skip when finished) a 3DGS model of a workspace; returns a summary.

    Writes ``train/split.json``, ``train/checkpoint.pt`` (periodically, atomically),
    ``train/model.pt`` (final), ``train/config.json`` and, with ``cfg.evaluate``, ``metrics.json``.

    Example:
        >>> summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))  # doctest: +SKIP
    """
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    cfg = cfg or TrainConfig()
    rc = cfg.resolved()
    paths = _paths(ws, cfg)
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)  # torch's ops; numba keeps its own
    note = plantsplat.omp_wait_policy_note()
    if note:
        log.warning("%s", note)

    if paths["model"].is_file() and not cfg.force:
        blob = load_checkpoint(paths["model"])
        done = blob["extra"].get("config", {})
        if done.get("mode") != rc.mode:
            raise PlantsplatError(
                f"{paths['model']}: holds a finished {done.get('mode')!r}-mode model; pass --force to retrain in "
                f"{rc.mode!r} mode, or --train-dir to keep both"
            )
        log.info("%s: finished model found (%d steps); skipping training (--force retrains)",
                 paths["model"], blob["step"])
        summary = dict(blob["extra"].get("summary", {}))
        if cfg.evaluate and not paths["metrics"].is_file():
            from plantsplat.train.evaluate import evaluate_workspace

            summary["metrics"] = evaluate_workspace(ws, train_dir=paths["dir"], metrics_path=paths["metrics"],
                                                    lpips_weights=cfg.lpips_weights, backend=rc.backend,
                                                    train_summary=summary)
        return summary

    object_mode = rc.mode == "object"
    scene = D.load_scene(ws, need_masks=object_mode)
    names = [v.name for v in scene.views]
    split = D.load_or_make_split(paths["split"], names, cfg.test_fraction, cfg.test_every)
    train_views = [v for v in scene.views if v.name in set(split["train"])]
    if not train_views:
        raise PlantsplatError(f"{paths['split']}: no training frame has a pose; delete it and re-run")
    log.info("%d training and %d test frames (%s); poses from %s", len(train_views), len(split["test"]),
             split["method"], scene.pose_source)

    sscale = scene_scale(scene.views)
    sched = rc.schedule()
    strategy = DensityStrategy(
        prune_opa=0.1, refine_start_iter=sched["refine_start"], refine_stop_iter=sched["refine_stop"],
        refine_every=sched["refine_every"], reset_every=sched["reset_every"],
        max_gaussians=rc.max_gaussians,
    )
    rc.strategy = asdict(strategy)
    max_side = max(max(v.width, v.height) for v in scene.views)
    base_scale = min(1.0, rc.max_resolution / max_side) if rc.max_resolution else 1.0
    device = torch.device("cuda" if rc.backend == "gsplat" else "cpu")
    cache = ImageCache(scene.views, base_scale, device)

    rng = np.random.default_rng(rc.seed)
    torch.manual_seed(rc.seed)
    start = 0
    resumed = False
    nonfinite = {"steps": 0, "gaussians": 0}  # steps whose gradients had NaN/inf entries (see _drop_nonfinite_grads)
    if paths["ckpt"].is_file() and not cfg.force:
        blob = load_checkpoint(paths["ckpt"])
        old = blob["extra"].get("config", {})
        if old.get("mode") != rc.mode or old.get("iterations") != rc.iterations:
            raise PlantsplatError(
                f"{paths['ckpt']}: an unfinished {old.get('mode')!r}-mode run of {old.get('iterations')} steps; "
                "re-run with the same options to resume it, or pass --force to start again"
            )
        params = params_from_checkpoint(blob).to(device)
        optimizers = make_optimizers(params, _lrs(rc, sscale))
        for k, o in optimizers.items():
            o.load_state_dict(blob["optimizers"][k])
        state = dict(blob["strategy_state"])
        start = int(blob["step"])
        elapsed0 = float(blob["extra"].get("train_seconds", 0.0))
        if "rng" in blob["extra"]:
            rng.bit_generator.state = blob["extra"]["rng"]
        resumed = True
        occ = _occluders_from(blob["extra"].get("occluders"), device)
        nonfinite.update(blob["extra"].get("nonfinite_grads", {}))
        log.info("resuming %s from step %d of %d (%d Gaussians)", paths["ckpt"], start, rc.iterations,
                 params["means"].shape[0])
    else:
        pts, cols, how = D.initial_points(scene, train_views, object_mode, cfg.init_points, rng)
        params = init_params(pts, cols, rc.sh_degree, rc.init_opacity, seed=rc.seed).to(device)
        optimizers = make_optimizers(params, _lrs(rc, sscale))
        state = strategy.initialize_state(sscale)
        elapsed0 = 0.0
        log.info("initialised %d Gaussians from %s; scene scale %.1f", len(pts), how, sscale)
        occ = None
        if object_mode and cfg.occluders:
            opts = D.occluder_points(scene, train_views)
            if len(opts) >= 20:
                occ = _occluders_from(_tensors(init_params(opts, np.full((len(opts), 3), 0.5), 0, _OCC_OPACITY,
                                                           init_scale=_OCC_SCALE, seed=rc.seed + 1)), device)
                log.info("%d occluders from the SfM points the masks leave out near the object", len(opts))
    write_json_atomic(paths["config"], {"requested": _jsonable(asdict(cfg)), "resolved": asdict(rc)})

    extra_base = {"config": asdict(rc), "split": split}
    occ_opt = None
    if occ is not None:
        lr = _lrs(rc, sscale)
        occ_opt = make_optimizers(occ, {k: lr[k] for k in occ.keys()})
    means_decay = (rc.lr_means_final / rc.lr_means) ** (1.0 / max(1, rc.iterations))
    order: list[int] = []
    last_good = start
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    last_ckpt = t_start
    loss_ema = psnr_ema = None
    bad_run = 0  # consecutive steps with non-finite gradients

    def checkpoint(step: int) -> None:
        extra = dict(extra_base, train_seconds=elapsed0 + time.perf_counter() - t_start,
                     rng=rng.bit_generator.state, occluders=_tensors(occ), nonfinite_grads=dict(nonfinite))
        save_checkpoint(paths["ckpt"], step, params, optimizers, state, extra)

    with make_progress() as bar:
        task = bar.add_task(f"training ({rc.mode})", total=rc.iterations, completed=start, info="")
        step = start
        for step in range(start, rc.iterations):
            if not order:
                order = list(rng.permutation(len(train_views)))
            view = train_views[order.pop()]
            down = 2 ** max(0, rc.num_downscales - step // sched["res_interval"])
            sh_deg = min(rc.sh_degree, step // sched["sh_interval"])
            img, alpha, K, w, h = cache.get(view.name, down)
            viewmat = torch.tensor(view.viewmat, dtype=torch.float32, device=device)
            if object_mode and rc.crop:
                x0, y0, x1, y1 = cache.box(view.name, down)
            else:
                x0, y0, x1, y1 = 0, 0, w, h
            Kc = K.clone()
            Kc[0, 2] -= x0
            Kc[1, 2] -= y0
            gt = img[y0:y1, x0:x1]  # [h', w', 3]
            bg = torch.from_numpy(rng.random(3)).float().to(device)  # [3] random background each step
            # object mode: the frame composited over bg through its mask (in the loss kernel's first pass on the CPU)
            gt_alpha = alpha[y0:y1, x0:x1] if object_mode else None  # [h', w', 1]

            for o in [optimizers["means"]] + ([occ_opt["means"]] if occ_opt else []):
                for g in o.param_groups:
                    g["lr"] = rc.lr_means * sscale * means_decay**step
            try:
                out = render(params, viewmat, Kc, x1 - x0, y1 - y0, sh_deg, rc.backend, occ, bg)
            except PlantsplatError as exc:  # non-finite parameters: the previous step diverged
                _diverged(paths, last_good, exc, "the model's parameters became NaN/inf")
            n_model = params["means"].shape[0]
            strategy.step_pre_backward(params, optimizers, state, step, out)
            # render composited over bg, [h', w', 3], against gt: (1 - l) L1 + l (1 - SSIM)
            loss, mse = photometric_loss(out.color, out.alpha, bg, gt, rc.ssim_lambda, gt_alpha)
            if not torch.isfinite(loss):
                _diverged(paths, last_good, None)
            loss.backward()
            bad, where = _drop_nonfinite_grads([("", params), ("occluder ", occ)], out.means2d)
            if bad:
                nonfinite["steps"] += 1
                nonfinite["gaussians"] += bad
                bad_run += 1
                if nonfinite["steps"] == 1:
                    log.warning("step %d: NaN/inf gradients (%s) for %d Gaussians; their update is skipped this step "
                                "(counted in the summary as nonfinite_grad_steps)", step, ", ".join(where), bad)
                if bad_run >= _MAX_NONFINITE_RUN:
                    _diverged(paths, last_good, None, f"the gradients were NaN/inf {bad_run} steps in a row")
            else:
                bad_run = 0
            # grads are w.r.t. crop pixels; normalise by the full (downscaled) image size as gsplat
            strategy.step_post_backward(params, optimizers, state, step, _ModelPart(out, n_model), w, h)
            for o in list(optimizers.values()) + list((occ_opt or {}).values()):
                o.step()
                o.zero_grad(set_to_none=True)

            with torch.no_grad():
                lv = float(loss)
                pv = float(-10 * torch.log10(mse.clamp_min(1e-10)))
            loss_ema = lv if loss_ema is None else 0.9 * loss_ema + 0.1 * lv
            psnr_ema = pv if psnr_ema is None else 0.9 * psnr_ema + 0.1 * pv
            bar.update(task, completed=step + 1,
                       info=f"loss {loss_ema:.4f}  PSNR {psnr_ema:5.2f}  {params['means'].shape[0]:,} Gaussians  1/{down}")
            now = time.perf_counter()
            if now - last_ckpt > cfg.checkpoint_seconds:
                checkpoint(step + 1)
                last_good = step + 1
                last_ckpt = now
            if step % max(1, rc.iterations // 10) == 0:
                log.debug("step %d loss %.4f psnr %.2f n=%d", step, loss_ema, psnr_ema, params["means"].shape[0])

    culled = strategy.final_cull(params, optimizers)
    if occ is not None:  # occluders that stayed transparent hide nothing
        with torch.no_grad():
            keep = torch.sigmoid(occ["opacities"]) >= strategy.prune_opa
            occ = _occluders_from({k: v[keep] for k, v in _tensors(occ).items()}, device)
    train_seconds = elapsed0 + time.perf_counter() - t_start
    n_final = int(params["means"].shape[0])
    log.info("trained %d steps in %.1f s; %d Gaussians (%d culled below opacity %.2f)", rc.iterations,
             train_seconds, n_final, culled, strategy.prune_opa)
    summary = {
        "mode": rc.mode, "backend": rc.backend, "preset": rc.preset, "iterations": rc.iterations,
        "train_seconds": round(train_seconds, 2), "n_gaussians": n_final, "resumed": resumed,
        # CPU seconds of this process (this session only): wall time is inflated on a busy machine
        "train_cpu_seconds": round(time.process_time() - cpu_start, 2),
        "train_resolution_scale": base_scale, "final_loss": loss_ema, "final_train_psnr": psnr_ema,
        "scene_scale": sscale,
        "nonfinite_grad_steps": nonfinite["steps"], "nonfinite_grad_gaussians": nonfinite["gaussians"],
    }
    save_checkpoint(paths["model"], rc.iterations, params, optimizers, state,
                    dict(extra_base, summary=summary, train_seconds=train_seconds, occluders=_tensors(occ)))
    paths["ckpt"].unlink(missing_ok=True)
    if cfg.evaluate:
        from plantsplat.train.evaluate import evaluate_workspace

        summary["metrics"] = evaluate_workspace(ws, train_dir=paths["dir"], metrics_path=paths["metrics"],
                                                lpips_weights=cfg.lpips_weights, backend=rc.backend,
                                                train_summary=summary, scene=scene)
    return summary


def _tensors(p) -> dict | None:
    """Detached copies of the geometry of a parameter dict (occluders: no colours), or None."""
    if p is None:
        return None
    return {k: p[k].detach().clone().cpu() for k in ("means", "scales", "quats", "opacities")}


def _occluders_from(t: dict | None, device) -> torch.nn.ParameterDict | None:
    """Occluder parameters from :func:`_tensors`' dict (None: no occluders)."""
    if not t or not t["means"].shape[0]:
        return None
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v.clone().to(device)) for k, v in t.items()})


# A step whose gradients have NaN/inf entries has those Gaussians' gradients zeroed (Adam's update of them is
# then its momentum alone, finite); training stops as diverged only when this lasts this many steps in a row.
_MAX_NONFINITE_RUN = 20


def _drop_nonfinite_grads(groups, means2d) -> tuple[int, list[str]]:
    """Zero every gradient of the Gaussians that have a NaN/inf gradient entry; returns their number and
    the parameters it was found in.

    ``groups`` are ``(label, ParameterDict or None)`` in the render's order (the model, then the occluders), whose
    rows are Gaussians; ``means2d`` is the render's screen-space means (its gradient feeds the density
    strategy, so it is cleaned too). One NaN in a pixel's gradient reaches every Gaussian drawn there, and a
    single such step used to leave NaN means after Adam's update, which stopped the run (``training
    diverged``) although the loss was finite. A finite sum of a gradient means it has no NaN/inf: the
    per-entry check runs only when a sum is not finite, and all sums are read at once (one GPU sync a step).
    """
    g2 = getattr(means2d, "grad", None)
    parts, offset = [], 0
    for label, p in groups:
        if p is None:
            continue
        n = p["means"].shape[0]
        grads = [(k, t.grad) for k, t in p.items() if t.grad is not None]
        if g2 is not None and g2.shape[0] >= offset + n:
            grads.append(("means2d", g2[offset:offset + n]))
        parts.append((label, n, grads))
        offset += n
    sums = [g.sum() for _, _, grads in parts for _, g in grads]
    if not sums:
        return 0, []
    finite = torch.isfinite(torch.stack(sums))
    if bool(finite.all()):
        return 0, []
    finite = iter(finite.tolist())  # in the order of the sums
    total, where = 0, []
    for label, n, grads in parts:
        bad = None
        for k, g in grads:
            if next(finite):
                continue
            rows = ~torch.isfinite(g).reshape(n, -1).all(dim=1)
            if bool(rows.any()):
                bad = rows if bad is None else bad | rows
                where.append(label + k)
        if bad is not None:
            for _, g in grads:
                g[bad] = 0.0
            total += int(bad.sum())
    return total, where


def _diverged(paths: dict, last_good: int, exc: Exception | None, what: str = "the loss became NaN/inf"):
    what += f" ({exc})" if exc else ""
    kept = f"the last good checkpoint (step {last_good}) is kept in {paths['ckpt']}" if paths["ckpt"].is_file() else \
        "no checkpoint was written yet"
    raise PlantsplatError(
        f"training diverged: {what}; {kept}; lower the learning rates or check the "
        "frames and poses, then re-run (or pass --force to start again)"
    )


def _lrs(rc: ResolvedConfig, sscale: float) -> dict[str, float]:
    return {"means": rc.lr_means * sscale, "scales": rc.lr_scales, "quats": rc.lr_quats,
            "opacities": rc.lr_opacities, "sh0": rc.lr_sh0, "shN": rc.lr_shN}


def _jsonable(d: dict) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


def load_model(ws: Workspace, train_dir: Path | None = None) -> tuple[torch.nn.ParameterDict, dict]:
    """The finished model of a workspace: parameters and the checkpoint's ``extra`` (config, split)."""
    p = model_path(ws, train_dir)
    if not p.is_file():
        ck = p.parent / "checkpoint.pt"
        hint = " (an unfinished run's checkpoint exists: re-run it to finish)" if ck.is_file() else ""
        raise PlantsplatError(f"{p}: no trained model{hint}; run `plantsplat train {ws.root}` first")
    blob = load_checkpoint(p)
    return params_from_checkpoint(blob), blob["extra"]



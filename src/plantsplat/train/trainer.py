"""The training loop: object-centric (RGBA, random background) or full-frame 3DGS, resumable.

Object mode (the paper, section 2.3): every step renders a training view, composites it over a
random colour ``B`` (``C_hat = C_splat + (1 - alpha_acc) * B``) and compares it with the frame
composited over the same ``B`` through its mask (``C = alpha_img * I + (1 - alpha_img) * B``), with
``(1 - 0.2) * L1 + 0.2 * (1 - SSIM)`` (:mod:`plantsplat.train.loss`). Outside the mask the target is
``B`` itself, which changes every step, so the only way to match it is transparency: Gaussians there
lose opacity and are culled below 0.1. Full mode is plain RGB 3DGS on whole frames (the paper's
Splatfacto baseline); PBR is the full model evaluated with the masks applied after training (see
:mod:`plantsplat.train.evaluate`).

Usage:
    from plantsplat.workspace import Workspace
    summary = train_workspace(Workspace("ws/plant_01"), TrainConfig(iterations=500))
    summary["n_gaussians"]
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

import plantsplat
from plantsplat.errors import PlantsplatError
from plantsplat.io import os_error_message, remove_tree, replace_dir, write_json_atomic
from plantsplat.log import get_logger, make_progress
from plantsplat.resources import usable_cores
from plantsplat.train import data as D
from plantsplat.train.checkpoint import (
    STAGED_METRICS,
    load_checkpoint,
    params_from_checkpoint,
    partial_paths,
    save_checkpoint,
    train_paths,
)
from plantsplat.train.config import ResolvedConfig, TrainConfig
from plantsplat.train.evaluate import evaluate_workspace
from plantsplat.train.loss import (
    MAX_NONFINITE_RUN,
    drop_nonfinite_grads,
    photometric_loss,
)
from plantsplat.train.model import init_params, make_optimizers
from plantsplat.train.render import (
    OCCLUDER_OPACITY,
    OCCLUDER_SCALE,
    ImageCache,
    occluder_tensors,
    occluders_from,
    render,
)
from plantsplat.train.strategy import DensityStrategy
from plantsplat.workspace import Workspace

log = get_logger(__name__)


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


@dataclass
class _Setup:
    """What a run trains on: the views, the split, the schedule and the image cache."""

    scene: D.Scene
    split: dict
    train_views: list
    sscale: float
    sched: dict
    strategy: DensityStrategy
    base_scale: float
    device: torch.device
    cache: ImageCache


@dataclass
class _State:
    """What a run changes as it goes (all of it in each checkpoint)."""

    params: torch.nn.ParameterDict
    optimizers: dict
    strategy_state: dict
    occ: torch.nn.ParameterDict | None
    rng: np.random.Generator
    start: int = 0
    elapsed0: float = 0.0
    resumed: bool = False
    nonfinite: dict = field(default_factory=lambda: {"steps": 0, "gaussians": 0})


def train_workspace(ws: Workspace | str | os.PathLike, cfg: TrainConfig | None = None, resume: bool = False,
                    scene: D.Scene | None = None) -> dict:
    """Train a 3DGS model of a workspace; returns a summary.

    ``resume``: go on from ``train/checkpoint.pt`` of an interrupted run with the same options and
    inputs (:func:`plantsplat.pipeline.train_stage` decides); otherwise training starts afresh.
    ``scene``: the frames to train on, as :func:`plantsplat.train.data.training_scene` gives them for ``cfg.mode``,
    loaded by a caller that uses them after training too (default: loaded here).
    Trains in ``.train.partial/`` (``split.json``, ``checkpoint.pt`` periodically and atomically, ``model.pt``,
    ``config.json``, ``renders/``), which replaces ``train/`` whole once the model and, with ``cfg.evaluate``,
    its metrics are complete; then ``metrics.json``. Until then the previous outputs stay as they were.

    Usage:
        summary = train_workspace("ws/plant_01", TrainConfig(mode="object"))
    """
    ws = ws if isinstance(ws, Workspace) else Workspace(ws)
    cfg = cfg or TrainConfig()
    rc = cfg.resolved()
    final = train_paths(ws, cfg)
    paths = partial_paths(final)  # the previous model stays in final["dir"] until this run is complete
    torch.set_num_threads(cfg.threads or usable_cores())  # torch's ops; numba keeps its own
    note = plantsplat.omp_wait_policy_note()
    if note:
        log.warning("%s", note)
    if not resume:  # a fresh run: nothing of an earlier unfinished one is reused
        remove_tree(paths["dir"])
    setup = _setup(ws, cfg, rc, paths, scene)
    st = _resume(paths, rc, setup) if resume and paths["ckpt"].is_file() else _initial_state(cfg, rc, setup)
    write_json_atomic(paths["config"], {"requested": _jsonable(asdict(cfg)), "resolved": asdict(rc)})
    t_start, cpu_start = time.perf_counter(), time.process_time()
    loss_ema, psnr_ema = _loop(st, setup, rc, cfg, paths, t_start)
    summary = _finish(ws, cfg, rc, paths, setup, st, time.perf_counter() - t_start, time.process_time() - cpu_start,
                      loss_ema, psnr_ema)
    _publish(paths, final, cfg.evaluate)
    return summary


def _publish(paths: dict, final: dict, metrics: bool) -> None:
    """Swap the finished run's folder in for the train folder, then its metrics in for ``metrics.json``."""
    try:
        replace_dir(paths["dir"], final["dir"])
        if metrics:
            shutil.move(final["dir"] / STAGED_METRICS, final["metrics"])
    except OSError as exc:
        raise PlantsplatError(os_error_message(exc, final["dir"])) from exc


def _setup(ws: Workspace, cfg: TrainConfig, rc: ResolvedConfig, paths: dict, scene: D.Scene | None) -> _Setup:
    scene = scene if scene is not None else D.training_scene(ws, rc.mode)
    split = D.load_or_make_split(paths["split"], [v.name for v in scene.views], cfg.test_fraction, cfg.test_every)
    train_views = [v for v in scene.views if v.name in set(split["train"])]
    if not train_views:
        raise PlantsplatError(f"{paths['split']}: no training frame has a pose; delete it and re-run")
    log.info("%d training and %d test frames (%s); poses from %s", len(train_views), len(split["test"]),
             split["method"], scene.pose_source)
    sched = rc.schedule()
    strategy = DensityStrategy(
        prune_opa=0.1, refine_start_iter=sched["refine_start"], refine_stop_iter=sched["refine_stop"],
        refine_every=sched["refine_every"], reset_every=sched["reset_every"], max_gaussians=rc.max_gaussians,
    )
    rc.strategy = asdict(strategy)
    max_side = max(max(v.width, v.height) for v in scene.views)
    base_scale = min(1.0, rc.max_resolution / max_side) if rc.max_resolution else 1.0
    device = torch.device("cuda" if rc.backend == "gsplat" else "cpu")
    return _Setup(scene, split, train_views, scene_scale(scene.views), sched, strategy, base_scale, device,
                  ImageCache(scene.views, base_scale, device))


def _initial_state(cfg: TrainConfig, rc: ResolvedConfig, s: _Setup) -> _State:
    rng = np.random.default_rng(rc.seed)
    torch.manual_seed(rc.seed)
    object_mode = rc.mode == "object"
    pts, cols, how = D.initial_points(s.scene, s.train_views, object_mode, cfg.init_points, rng)
    params = init_params(pts, cols, rc.sh_degree, rc.init_opacity, seed=rc.seed).to(s.device)
    log.info("initialised %d Gaussians from %s; scene scale %.1f", len(pts), how, s.sscale)
    occ = None
    if object_mode and cfg.occluders:
        opts = D.occluder_points(s.scene, s.train_views)
        if len(opts) >= 20:
            occ = occluders_from(occluder_tensors(init_params(opts, np.full((len(opts), 3), 0.5), 0, OCCLUDER_OPACITY,
                                                              init_scale=OCCLUDER_SCALE, seed=rc.seed + 1)), s.device)
            log.info("%d occluders from the SfM points the masks leave out near the object", len(opts))
    return _State(params, make_optimizers(params, _lrs(rc, s.sscale)), s.strategy.initialize_state(s.sscale), occ, rng)


def _resume(paths: dict, rc: ResolvedConfig, s: _Setup) -> _State:
    rng = np.random.default_rng(rc.seed)
    torch.manual_seed(rc.seed)
    blob = load_checkpoint(paths["ckpt"])
    old = blob["extra"].get("config", {})
    if old.get("mode") != rc.mode or old.get("iterations") != rc.iterations:
        raise PlantsplatError(
            f"{paths['ckpt']}: an unfinished {old.get('mode')!r}-mode run of {old.get('iterations')} steps; "
            "re-run with the same options to resume it, or pass --force to start again"
        )
    params = params_from_checkpoint(blob).to(s.device)
    optimizers = make_optimizers(params, _lrs(rc, s.sscale))
    for k, o in optimizers.items():
        o.load_state_dict(blob["optimizers"][k])
    if "rng" in blob["extra"]:
        rng.bit_generator.state = blob["extra"]["rng"]
    st = _State(params, optimizers, dict(blob["strategy_state"]), occluders_from(blob["extra"].get("occluders"), s.device),
                rng, start=int(blob["step"]), elapsed0=float(blob["extra"].get("train_seconds", 0.0)), resumed=True)
    st.nonfinite.update(blob["extra"].get("nonfinite_grads", {}))
    log.info("resuming %s from step %d of %d (%d Gaussians)", paths["ckpt"], st.start, rc.iterations,
             params["means"].shape[0])
    return st


def _loop(st: _State, s: _Setup, rc: ResolvedConfig, cfg: TrainConfig, paths: dict, t_start: float):
    """The training steps from ``st.start``; returns the final smoothed loss and PSNR."""
    occ_opt = None
    if st.occ is not None:
        lr = _lrs(rc, s.sscale)
        occ_opt = make_optimizers(st.occ, {k: lr[k] for k in st.occ.keys()})
    means_decay = (rc.lr_means_final / rc.lr_means) ** (1.0 / max(1, rc.iterations))
    order: list[int] = []
    last_good, last_ckpt = st.start, t_start
    loss_ema = psnr_ema = None
    bad_run = 0  # consecutive steps with non-finite gradients
    with make_progress() as bar:
        task = bar.add_task(f"training ({rc.mode})", total=rc.iterations, completed=st.start, info="")
        for step in range(st.start, rc.iterations):
            if not order:
                order = list(st.rng.permutation(len(s.train_views)))
            view = s.train_views[order.pop()]
            down = 2 ** max(0, rc.num_downscales - step // s.sched["res_interval"])
            for o in [st.optimizers["means"]] + ([occ_opt["means"]] if occ_opt else []):
                for g in o.param_groups:
                    g["lr"] = rc.lr_means * s.sscale * means_decay**step
            loss, mse, bad, where = _step(st, s, rc, view, down, step, occ_opt, paths, last_good)
            if bad:
                st.nonfinite["steps"] += 1
                st.nonfinite["gaussians"] += bad
                bad_run += 1
                if st.nonfinite["steps"] == 1:
                    log.warning("step %d: NaN/inf gradients (%s) for %d Gaussians; their update is skipped this step "
                                "(counted in the summary as nonfinite_grad_steps)", step, ", ".join(where), bad)
                if bad_run >= MAX_NONFINITE_RUN:
                    _diverged(paths, last_good, None, f"the gradients were NaN/inf {bad_run} steps in a row")
            else:
                bad_run = 0
            lv, pv = float(loss), float(-10 * torch.log10(mse.clamp_min(1e-10)))
            loss_ema = lv if loss_ema is None else 0.9 * loss_ema + 0.1 * lv
            psnr_ema = pv if psnr_ema is None else 0.9 * psnr_ema + 0.1 * pv
            n = st.params["means"].shape[0]
            bar.update(task, completed=step + 1, info=f"loss {loss_ema:.4f}  PSNR {psnr_ema:5.2f}  {n:,} Gaussians  1/{down}")
            now = time.perf_counter()
            if now - last_ckpt > cfg.checkpoint_seconds:
                _checkpoint(st, s, rc, paths, step + 1, t_start)
                last_good, last_ckpt = step + 1, now
            if step % max(1, rc.iterations // 10) == 0:
                log.debug("step %d loss %.4f psnr %.2f n=%d", step, loss_ema, psnr_ema, n)
    return loss_ema, psnr_ema


def _step(st: _State, s: _Setup, rc: ResolvedConfig, view, down: int, step: int, occ_opt, paths: dict, last_good: int):
    """One optimisation step on ``view`` at 1/``down`` resolution; returns the loss, the MSE and the non-finite
    gradients dropped (count, where)."""
    object_mode = rc.mode == "object"
    img, alpha, K, w, h = s.cache.get(view.name, down)
    viewmat = torch.tensor(view.viewmat, dtype=torch.float32, device=s.device)
    x0, y0, x1, y1 = s.cache.box(view.name, down) if object_mode and rc.crop else (0, 0, w, h)
    Kc = K.clone()
    Kc[0, 2] -= x0
    Kc[1, 2] -= y0
    gt = img[y0:y1, x0:x1]  # [h', w', 3]
    bg = torch.from_numpy(st.rng.random(3)).float().to(s.device)  # [3] random background each step
    # object mode: the frame composited over bg through its mask (in the loss kernel's first pass on the CPU)
    gt_alpha = alpha[y0:y1, x0:x1] if object_mode else None  # [h', w', 1]
    sh_deg = min(rc.sh_degree, step // s.sched["sh_interval"])
    try:
        out = render(st.params, viewmat, Kc, x1 - x0, y1 - y0, sh_deg, rc.backend, st.occ, bg)
    except PlantsplatError as exc:  # non-finite parameters: the previous step diverged
        _diverged(paths, last_good, exc, "the model's parameters became NaN/inf")
    n_model = st.params["means"].shape[0]
    s.strategy.step_pre_backward(st.params, st.optimizers, st.strategy_state, step, out)
    # render composited over bg, [h', w', 3], against gt: (1 - l) L1 + l (1 - SSIM)
    loss, mse = photometric_loss(out.color, out.alpha, bg, gt, rc.ssim_lambda, gt_alpha)
    if not torch.isfinite(loss):
        _diverged(paths, last_good, None)
    loss.backward()
    bad, where = drop_nonfinite_grads([("", st.params), ("occluder ", st.occ)], out.means2d)
    # grads are w.r.t. crop pixels; normalise by the full (downscaled) image size as gsplat
    s.strategy.step_post_backward(st.params, st.optimizers, st.strategy_state, step, _ModelPart(out, n_model), w, h)
    for o in list(st.optimizers.values()) + list((occ_opt or {}).values()):
        o.step()
        o.zero_grad(set_to_none=True)
    return loss.detach(), mse, bad, where


def _checkpoint(st: _State, s: _Setup, rc: ResolvedConfig, paths: dict, step: int, t_start: float) -> None:
    extra = {"config": asdict(rc), "split": s.split, "train_seconds": st.elapsed0 + time.perf_counter() - t_start,
             "rng": st.rng.bit_generator.state, "occluders": occluder_tensors(st.occ), "nonfinite_grads": dict(st.nonfinite)}
    save_checkpoint(paths["ckpt"], step, st.params, st.optimizers, st.strategy_state, extra)


def _finish(ws: Workspace, cfg: TrainConfig, rc: ResolvedConfig, paths: dict, s: _Setup, st: _State, wall: float,
            cpu: float, loss_ema, psnr_ema) -> dict:
    """The final cull, ``model.pt`` and the summary (with the test views' metrics when ``cfg.evaluate``)."""
    culled = s.strategy.final_cull(st.params, st.optimizers)
    occ = st.occ
    if occ is not None:  # occluders that stayed transparent hide nothing
        with torch.no_grad():
            keep = torch.sigmoid(occ["opacities"]) >= s.strategy.prune_opa
            occ = occluders_from({k: v[keep] for k, v in occluder_tensors(occ).items()}, s.device)
    train_seconds = st.elapsed0 + wall
    n_final = int(st.params["means"].shape[0])
    log.info("trained %d steps in %.1f s; %d Gaussians (%d culled below opacity %.2f)", rc.iterations,
             train_seconds, n_final, culled, s.strategy.prune_opa)
    summary = {
        "mode": rc.mode, "backend": rc.backend, "preset": rc.preset, "iterations": rc.iterations,
        "train_seconds": round(train_seconds, 2), "n_gaussians": n_final, "resumed": st.resumed,
        # CPU seconds of this process (this run only, not the resumed ones): wall time is inflated on a busy machine
        "train_cpu_seconds": round(cpu, 2),
        "train_resolution_scale": s.base_scale, "final_loss": loss_ema, "final_train_psnr": psnr_ema,
        "scene_scale": s.sscale,
        "nonfinite_grad_steps": st.nonfinite["steps"], "nonfinite_grad_gaussians": st.nonfinite["gaussians"],
    }
    save_checkpoint(paths["model"], rc.iterations, st.params, st.optimizers, st.strategy_state,
                    {"config": asdict(rc), "split": s.split, "summary": summary, "train_seconds": train_seconds,
                     "occluders": occluder_tensors(occ)})
    paths["ckpt"].unlink(missing_ok=True)
    if cfg.evaluate:
        summary["metrics"] = evaluate_workspace(ws, train_dir=paths["dir"], metrics_path=paths["metrics"],
                                                lpips_weights=cfg.lpips_weights, backend=rc.backend,
                                                train_summary=summary, scene=s.scene)
    return summary


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

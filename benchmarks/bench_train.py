"""Benchmark: object-centric vs full-frame vs PBR 3DGS on synthetic captures and the ROMI virtual plant.

Reproduces the paper's comparison (Tables 2-3): for each capture, train `object` and `full` models
with the same split; PBR is the full model evaluated with the masks applied after training. Records
PSNR / SSIM / LPIPS (full frame and foreground only), training wall and CPU time, render FPS,
Gaussians and peak memory, plus machine info (timings on a shared machine are noisy).

Two PBR figures: `pbr` clips the render with the test frame's own (here: ground-truth) mask, an upper
bound; `pbr_segmented` is the paper's PBR, the renders segmented after training (the paper: SAM-2;
here: plantsplat's 3d segmenter). Its fair opponent is `object_segmented` (synthetic captures, unless
--no-segmented): the object model trained on plantsplat's segmenter's masks of the frames, as the paper
trains on SAM-2's, scored against the same ground-truth-masked test frames as every other row.

    .venv/bin/python benchmarks/bench_train.py                       # the benchmark as recorded (slow)
    .venv/bin/python benchmarks/bench_train.py --poses sfm --skip-romi --out /tmp/train_sfm.json
        # the same captures through the poses stage: COLMAP cameras and SfM points for both modes
    .venv/bin/python benchmarks/bench_train.py --frames 36 --width 180 --height 320 --iterations 300
    .venv/bin/python benchmarks/bench_train.py --seeds 0 --modes object --skip-romi --frames 36 \
        --width 270 --height 480 --iterations 600 --out /tmp/train_quick.json   # training speed only

Writes benchmarks/results/train.json (atomically).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")

from plantsplat.io import read_json, write_json_atomic  # noqa: E402
from plantsplat.log import setup_logging  # noqa: E402
from plantsplat.resources import machine_info  # noqa: E402
from plantsplat.workspace import Workspace  # noqa: E402


def synth_workspace(cap: Path, dst: Path, poses: str = "true") -> tuple[Workspace, dict | None]:
    """Workspace from a synth capture with its ground-truth masks, and its ground-truth poses (``true``:
    no SfM points, so both modes start from random points) or the poses stage's (``sfm``: COLMAP poses
    and sparse points calibrated by the cube, as a user's run; both modes start from the SfM points,
    as the paper's Splatfacto baseline does). Returns the workspace and the poses report (sfm)."""
    from plantsplat.synth.groundtruth import true_transforms

    gt = read_json(cap / "ground_truth.json")
    ws = Workspace(dst)
    ws.images_dir.mkdir(parents=True)
    ws.masks_dir.mkdir(parents=True)
    kept = []
    for index, fr in enumerate(gt["frames"]):
        name = Path(fr["file"]).name
        shutil.copy(cap / fr["file"], ws.images_dir / name)
        shutil.copy(cap / fr["mask"], ws.masks_dir / name)
        kept.append((name, index))
    if poses == "sfm":
        from plantsplat.poses import stage as poses_stage

        t0 = time.perf_counter()
        rep = poses_stage.run(ws)
        return ws, {"seconds": round(time.perf_counter() - t0, 1), "registered": rep["registered"],
                    "total": rep["total"], "num_points": rep["num_points"],
                    "reprojection_px": rep["mean_reprojection_error_px"]}
    write_json_atomic(ws.transforms_json, true_transforms(gt, kept))
    return ws, None


def detail_reference(ws: Workspace, split_path: Path, sigmas=(0.5, 0.8, 1.0)) -> dict:
    """Foreground PSNR of each test frame against itself blurred by a Gaussian of ``sigma`` px, over
    the mask's pixels at the frames' own resolution (mean over test views): how much of the foreground's signal lies at
    the scale of
    a pixel, a yardstick for the models' foreground PSNR (a render as sharp as the frame blurred by
    0.8 px scores about the 0.8 figure)."""
    import cv2

    names = read_json(split_path)["test"]
    out = {}
    for sigma in sigmas:
        vals = []
        for name in names:
            img = cv2.imread(str(ws.images_dir / name)).astype(np.float64) / 255.0
            m = cv2.imread(str(ws.masks_dir / name), cv2.IMREAD_GRAYSCALE) > 127
            if not m.any():
                continue
            err = ((cv2.GaussianBlur(img, (0, 0), sigma) - img) ** 2)[m].mean()
            vals.append(-10.0 * np.log10(max(err, 1e-12)))
        out[f"blur_{sigma}px_psnr"] = float(np.mean(vals)) if vals else None
    return out


def object_ceiling(ws: Workspace, cap: Path, split_path: Path) -> dict:
    """The foreground metrics of an exact object model: the capture's ``objects/`` renders (the plant and cube alone
    over black, without the sensor's noise, blur and drift) scored against the test frames as
    :mod:`plantsplat.train.evaluate` scores a model (frame through its mask over black; PSNR and SSIM over the mask,
    PSNR over its interior). What a model could reach at best on these frames, at the frames' own resolution."""
    import cv2
    import torch

    from plantsplat.train.evaluate import foreground_scores

    gt = read_json(cap / "ground_truth.json")
    objects = {Path(fr["file"]).name: cap / fr["object"] for fr in gt["frames"]}
    rows = []
    for name in read_json(split_path)["test"]:
        m = cv2.imread(str(ws.masks_dir / name), cv2.IMREAD_GRAYSCALE)
        if not (m > 127).any():
            continue
        a = torch.from_numpy(m).float()[..., None] / 255.0
        img, obj = (torch.from_numpy(np.ascontiguousarray(cv2.imread(str(f))[..., ::-1])).float() / 255.0
                    for f in (ws.images_dir / name, objects[name]))
        rows.append(foreground_scores(obj, img * a, a))
    if not rows:
        return {}
    return {k: float(np.mean([r[k] for r in rows if r[k] is not None] or [np.nan])) for k in rows[0]} | \
        {"n_test_views": len(rows)}


def run_modes(ws: Workspace, iterations: int | None, max_res: int | None, modes=("object", "full")) -> dict:
    from plantsplat.train.config import TrainConfig
    from plantsplat.train.trainer import train_workspace

    res = {}
    for mode in modes:
        t0 = time.perf_counter()
        cfg = TrainConfig(mode=mode, iterations=iterations, max_resolution=max_res, train_dir=ws.root / f"train_{mode}",
                          metrics_path=ws.root / f"metrics_{mode}.json")
        s = train_workspace(ws, cfg)
        m = s["metrics"]
        res[mode] = {k: m[k] for k in ("composite", "foreground", "n_gaussians", "render_fps", "train_seconds",
                                        "train_cpu_seconds", "resolution", "iterations", "n_test_views")}
        res[mode]["peak_rss_mb_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        res[mode]["wall_seconds_incl_eval"] = time.perf_counter() - t0
        res[mode]["s_per_iteration"] = s["train_seconds"] / max(1, s["iterations"])
        res[mode]["cpu_s_per_iteration"] = s["train_cpu_seconds"] / max(1, s["iterations"])
        res[mode]["loadavg_after"] = os.getloadavg()
        res[mode]["nonfinite_grad_steps"] = s.get("nonfinite_grad_steps")  # steps whose NaN/inf gradients were dropped
        if mode == "full":
            res["pbr"] = m["pbr"]
            res["pbr_segmented"] = m.get("pbr_segmented")
        print(mode, {k: res[mode][k] for k in ("composite", "foreground", "n_gaussians", "train_seconds")}, flush=True)
    return res


def object_on_segmented_masks(ws: Workspace, iterations: int | None, max_res: int | None) -> dict:
    """The paper's setting with plantsplat's segmenter in place of SAM-2: a copy of ``ws`` (same frames and poses) whose
    masks come from ``plantsplat segment``, an object model trained on it, scored on ``ws``'s test views against their
    ground-truth masks (as the other rows). Also the segmenter's mask IoU against the truth over all frames."""
    import cv2

    from plantsplat.segment import stage as segmentation
    from plantsplat.segment.config import SegmentConfig
    from plantsplat.segment.scores import mask_iou
    from plantsplat.train.config import TrainConfig
    from plantsplat.train.evaluate import evaluate_workspace
    from plantsplat.train.trainer import train_workspace

    seg = Workspace(ws.root.parent / f"{ws.root.name}_segmented")
    shutil.copytree(ws.root, seg.root, ignore=lambda d, names: [n for n in names if n.startswith(("train_", "metrics_"))
                                                                  or n in ("masks", "rgba")])
    t0 = time.perf_counter()
    segmentation.run(seg, SegmentConfig(preview=False))
    seg_seconds = time.perf_counter() - t0
    ious = []
    for name in ws.image_names():
        t = cv2.imread(str(ws.masks_dir / name), cv2.IMREAD_GRAYSCALE) > 127
        m = cv2.imread(str(seg.masks_dir / name), cv2.IMREAD_GRAYSCALE) > 127
        ious.append(mask_iou(t, m))
    t0 = time.perf_counter()
    cfg = TrainConfig(mode="object", iterations=iterations, max_resolution=max_res, train_dir=seg.root / "train_object",
                      evaluate=False)
    s = train_workspace(seg, cfg)
    m = evaluate_workspace(ws, train_dir=seg.root / "train_object", metrics_path=ws.root / "metrics_object_segmented.json",
                           train_summary=s)
    same_split = read_json(seg.root / "train_object" / "split.json")["test"] == \
        read_json(ws.root / "train_object" / "split.json")["test"] if (ws.root / "train_object").is_dir() else None
    res = {k: m[k] for k in ("composite", "foreground", "n_gaussians", "render_fps", "train_seconds",
                             "train_cpu_seconds", "resolution", "iterations", "n_test_views")}
    res.update({"segment_seconds": round(seg_seconds, 1), "mask_iou_mean": float(np.mean(ious)),
                "mask_iou_min": float(np.min(ious)), "same_test_views_as_object": same_split,
                "wall_seconds_incl_eval": time.perf_counter() - t0, "loadavg_after": os.getloadavg(),
                "nonfinite_grad_steps": s.get("nonfinite_grad_steps")})
    print("object_segmented", {k: res[k] for k in ("composite", "foreground", "mask_iou_mean", "train_seconds")},
          flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=540)
    ap.add_argument("--height", type=int, default=960)
    ap.add_argument("--iterations", type=int, default=None, help="default: the CPU recipe's")
    ap.add_argument("--max-resolution", type=int, default=None)
    ap.add_argument("--romi-size", type=int, default=448)
    ap.add_argument("--skip-romi", action="store_true")
    ap.add_argument("--poses", choices=("true", "sfm"), default="true",
                    help="synthetic captures: ground-truth cameras and random initialisation (true), or the poses "
                         "stage's COLMAP cameras and sparse points, as a user's run (sfm)")
    ap.add_argument("--modes", nargs="+", choices=("object", "full"), default=["object", "full"],
                    help="which models to train (PBR needs full)")
    ap.add_argument("--no-segmented", action="store_true",
                    help="skip the object model trained on the segmenter's masks (object_segmented)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "train.json")
    args = ap.parse_args()
    setup_logging()
    from plantsplat.synth import SynthConfig, generate

    doc = {"machine_start": machine_info(), "args": {k: str(v) for k, v in vars(args).items()}, "synth": {},
           "romi": None}
    tmp = Path(tempfile.mkdtemp(prefix="bench_train_"))
    try:
        for seed in args.seeds:
            cap = tmp / f"cap{seed}"
            generate(SynthConfig(out=cap, seed=seed, frames=args.frames, width=args.width, height=args.height,
                                 object_renders=True, force=True))
            ws, poses = synth_workspace(cap, tmp / f"ws{seed}", args.poses)
            doc["synth"][str(seed)] = run_modes(ws, args.iterations, args.max_resolution, tuple(args.modes))
            if not args.no_segmented and "object" in args.modes:
                doc["synth"][str(seed)]["object_segmented"] = object_on_segmented_masks(ws, args.iterations,
                                                                                        args.max_resolution)
            split = ws.root / f"train_{args.modes[0]}" / "split.json"
            doc["synth"][str(seed)]["foreground_detail_reference"] = detail_reference(ws, split)
            doc["synth"][str(seed)]["foreground_exact_object_render"] = object_ceiling(ws, cap, split)
            if poses is not None:
                doc["synth"][str(seed)]["poses"] = poses
            doc["machine_end"] = machine_info()
            write_json_atomic(args.out, doc)
        ds = Path(os.environ.get("PLANTSPLAT_DATASETS", REPO.parent / "shared" / "datasets"))
        romi = ds / "romi_virtual_plant_synthetic"
        if not args.skip_romi and romi.is_dir():
            from plantsplat.train.romi import workspace_from_romi

            ws = workspace_from_romi(romi, tmp / "romi", size=args.romi_size)
            doc["romi"] = run_modes(ws, args.iterations, args.max_resolution, tuple(args.modes))
        elif not args.skip_romi:
            doc["romi"] = f"skipped: {romi} not found"
        # means over seeds
        summ = {}
        for key in ("object", "object_segmented", "full", "pbr", "pbr_segmented"):
            rows = [r[key] for r in doc["synth"].values() if r.get(key)]
            if not rows:
                continue
            if key.startswith("pbr"):
                summ[key] = {f"{k}": float(np.mean([r[k] for r in rows if r.get(k) is not None] or [np.nan]))
                             for k in ("psnr", "ssim", "lpips", "mask_iou") if k in rows[0]}
                continue
            summ[key] = {
                "composite": {k: float(np.mean([r["composite"][k] for r in rows if r["composite"][k] is not None]
                                               or [np.nan])) for k in ("psnr", "ssim", "lpips")},
                "foreground": {k: float(np.mean([r["foreground"].get(k) for r in rows
                                                 if r["foreground"].get(k) is not None] or [np.nan]))
                                for k in ("psnr", "ssim", "lpips", "psnr_interior")},
                **{k: float(np.mean([r[k] for r in rows])) for k in ("train_seconds", "train_cpu_seconds",
                                                                      "s_per_iteration", "cpu_s_per_iteration",
                                                                      "n_gaussians", "render_fps", "mask_iou_mean")
                   if k in rows[0]},
            }
        ceil = [r["foreground_exact_object_render"] for r in doc["synth"].values()
                if r.get("foreground_exact_object_render")]
        if ceil:
            summ["foreground_exact_object_render"] = {k: float(np.mean([c[k] for c in ceil]))
                                                      for k in ("psnr", "ssim", "psnr_interior")}
        doc["synth_mean"] = summ
        doc["machine_end"] = machine_info()
        write_json_atomic(args.out, doc)
        print("wrote", args.out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

"""Benchmark of `plantsplat segment`: mask quality against true masks, and the stage's time.

Every capture is run as a user runs it: the frames stage on its video (120 frames, 960 px), the
poses stage, then the segment stage with its defaults (the ``3d`` backend). Scored against the true
masks: the three foreign renders in ``../shared/datasets/foreign_renders/`` (masks of every 10th
video frame) and plantsplat's own synthetic captures of the given seeds (every frame; with
``--class-maps`` the errors by part too). Per capture: mean and worst frame IoU, IoU off the outline
(the 1 px band either side of the true outline left out of both masks), boundary F (2 px), how well
the segmenter's own per-frame confidence tells the bad frames (correlation with IoU), the stage's
seconds (its quick 3D model included), and how many of the Gaussians the stage called plant lie
farther than 2 cm from the true plant surface (the foreign renders' ``plant_points.npz``, the
synthetic captures' ``plant_gt.ply``; opaque ones, above 0.5, apart). Frames the poses stage could
not register have no mask and are counted apart. Also the ROMI virtual plant (no cube: the uncalibrated path) against its masks.

Writes ``benchmarks/results/segment.json`` with machine information and the date. Workspaces are
kept in ``--work`` so that a re-run reuses the poses (the segment stage always runs again).

Usage:
    .venv/bin/python benchmarks/bench_segment.py [--seeds 81 82 83 84 85] [--foreign 101 102 103 104 108 110] [--no-romi]
    .venv/bin/python benchmarks/bench_segment.py --e2e-work /tmp/plantsplat_bench_e2e  # the masks bench_e2e.py left
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_image, read_json, write_json_atomic
from plantsplat.segment import stage as segmentation
from plantsplat.segment.config import SegmentConfig
from plantsplat.segment.scores import mask_iou
from plantsplat.workspace import Workspace

ROOT = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("PLANTSPLAT_DATASETS", ROOT.parent / "shared" / "datasets"))
RESULTS = ROOT / "benchmarks" / "results" / "segment.json"
TARGETS = {"mean_iou_every_capture": 0.90, "worst_frame_iou": 0.75, "own_seeds_mean_iou": 0.88, "seconds_120_frames": 120.0,
           "plant_gaussians_far_share": 0.01}
FAR_CM = 2.0


def boundary_f(pred: np.ndarray, gt: np.ndarray, tol: int = 2) -> float:
    """Boundary F-score: boundary pixels of each mask within ``tol`` px of the other's boundary."""
    k = np.ones((3, 3), np.uint8)

    def edge(m):
        m8 = m.astype(np.uint8)
        return m8 - cv2.erode(m8, k)

    bp, bg = edge(pred), edge(gt)
    if bp.sum() == 0 or bg.sum() == 0:
        return float(bp.sum() == bg.sum())
    dg = cv2.distanceTransform(1 - bg, cv2.DIST_L2, 3)
    dp = cv2.distanceTransform(1 - bp, cv2.DIST_L2, 3)
    precision, recall = float((dg[bp > 0] <= tol).mean()), float((dp[bg > 0] <= tol).mean())
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def score(ws: Workspace, truth: dict[str, np.ndarray]) -> dict:
    """Scores of a segmented workspace against ``{frame name: true mask}`` (frames with a camera only)."""
    seg = read_json(ws.segment_json)
    conf = {r["name"]: r.get("confidence") for r in seg["frames"]}
    k3 = np.ones((3, 3), np.uint8)
    rows = []
    for name, gt in truth.items():
        if conf.get(name) is None:
            continue  # not registered: no camera, no mask
        m = read_image(ws.masks_dir / name, "gray") > 127
        g8 = gt.astype(np.uint8)
        band = (cv2.dilate(g8, k3) > 0) & ~(cv2.erode(g8, k3) > 0)
        rows.append((name, mask_iou(m, gt), mask_iou(m & ~band, gt & ~band), boundary_f(m, gt), conf[name]))
    iou = np.array([r[1] for r in rows])
    out = {"frames_scored": len(rows), "frames_without_camera": len(truth) - len(rows),
           "mean_iou": round(float(iou.mean()), 4), "worst_iou": round(float(iou.min()), 4),
           "worst_frame": rows[int(iou.argmin())][0], "median_iou": round(float(np.median(iou)), 4),
           "mean_iou_off_outline": round(float(np.mean([r[2] for r in rows])), 4),
           "boundary_f_2px": round(float(np.mean([r[3] for r in rows])), 4),
           "confidence_iou_correlation": round(float(np.corrcoef(iou, [r[4] for r in rows])[0, 1]), 3)
           if len(rows) > 2 else None,
           "seconds": seg["timing"]["total_s"], "scene_model_seconds": seg["timing"].get("scene_model_s"),
           "per_frame": [{"name": r[0], "iou": round(r[1], 4), "confidence": r[4]} for r in rows],
           "object": seg["capture"].get("object")}
    return out


def true_plant_points(cap: Path) -> np.ndarray:
    """The true plant surface of a capture, in our cube frame (cm). ``[P, 3]``"""
    from plantsplat.poses.evaluate import cube_from_world

    if (cap / "plant_points.npz").is_file():
        data = np.load(cap / "plant_points.npz")
        pts = np.asarray(data[data.files[0]], np.float64)
    else:
        import open3d as o3d

        pts = np.asarray(o3d.io.read_point_cloud(str(cap / "plant_gt.ply")).points)
    T = cube_from_world(json.loads((cap / "ground_truth.json").read_text()))
    return pts @ T[:3, :3].T + T[:3, 3]


def far_from_plant(ws: Workspace, truth: np.ndarray) -> dict:
    """Share of the Gaussians the segment stage called plant (all; opaque ones) farther than ``FAR_CM`` from ``truth``."""
    import torch
    from scipy.spatial import cKDTree

    from plantsplat.segment.stored import load_object

    obj, _ = load_object(ws)
    mu = obj.params["means"].numpy()[obj.plant]
    opaque = torch.sigmoid(obj.params["opacities"]).numpy().reshape(-1)[obj.plant] > 0.5
    far = cKDTree(truth).query(mu)[0] > FAR_CM
    return {"plant_gaussians": int(len(mu)), "far_share": round(float(far.mean()), 4) if len(mu) else None,
            "opaque_far_share": round(float(far[opaque].mean()), 4) if opaque.any() else None}


def prepare(video: Path, ws: Workspace) -> None:
    """Frames and poses as a user runs them (kept from an earlier run of this benchmark)."""
    from plantsplat.frames import FramesConfig
    from plantsplat.frames import stage as frames_stage
    from plantsplat.poses import stage as poses_stage

    if not ws.frames_json.is_file():
        frames_stage.run(ws, FramesConfig(num=120, max_size=960), video)
    if not ws.poses_json.is_file() or read_json(ws.poses_json).get("status") != "ok":
        poses_stage.run(ws)


FOREIGN_MASKS = "{:05d}.png"
"""The foreign renders' true masks, of every 10th video frame, by the frame's index."""
OWN_MASKS = "frame_{:05d}.png"
"""plantsplat's own captures' true masks, of every video frame."""


def true_masks(cap: Path, ws: Workspace, pattern: str) -> dict[str, np.ndarray]:
    """The true masks of ``ws``'s frames that ``cap`` holds (``cap/masks/`` + ``pattern`` of the video frame's index:
    :data:`FOREIGN_MASKS` or :data:`OWN_MASKS`), by frame name."""
    paths = {f["name"]: cap / "masks" / pattern.format(f["source_index"]) for f in read_json(ws.frames_json)["frames"]}
    return {name: read_image(p, "gray") > 127 for name, p in paths.items() if p.is_file()}


def foreign(cap: Path, ws: Workspace) -> dict:
    prepare(cap / "video.mp4", ws)
    truth = true_masks(cap, ws, FOREIGN_MASKS)
    segmentation.run(ws, SegmentConfig())
    return {**score(ws, truth), **far_from_plant(ws, true_plant_points(cap))}


def synthetic(seed: int, cache: Path, ws: Workspace) -> dict:
    from plantsplat.synth import SynthConfig, generate

    cap = cache / f"s{seed}"
    if not (cap / "ground_truth.json").is_file():
        generate(SynthConfig(out=cap, seed=seed, force=True))
    prepare(cap / "video.mp4", ws)
    truth = true_masks(cap, ws, OWN_MASKS)
    segmentation.run(ws, SegmentConfig())
    return {**score(ws, truth), **far_from_plant(ws, true_plant_points(cap))}


def kept_runs(work: Path) -> dict[str, dict]:
    """Scores of the masks that `bench_e2e.py`'s runs left in ``work`` (its ``--work``: ``foreign_NNN`` and the demo's
    ``demo``/``demo_SEED`` folders), the segment stage not run again."""
    rows = {}
    for d in sorted(p for p in work.iterdir() if p.is_dir()):
        if d.name.startswith("foreign_"):
            cap, ws, pattern = DATASETS / "foreign_renders" / d.name.split("_", 1)[1], Workspace(d), FOREIGN_MASKS
        elif d.name == "demo" or d.name.startswith("demo_"):
            cap, ws, pattern = d / "capture", Workspace(d / "workspace"), OWN_MASKS
        else:
            continue
        if not ws.segment_json.is_file() or not cap.is_dir():
            continue
        truth = true_masks(cap, ws, pattern)
        rows[d.name] = {**score(ws, truth), **far_from_plant(ws, true_plant_points(cap))}
    return rows


def romi_virtual(ws: Workspace) -> dict | None:
    """The ROMI scanner's virtual plant (18 views, no cube): its given cameras, the segmenter, its masks."""
    from plantsplat.poses import PosesConfig
    from plantsplat.poses import stage as poses_stage

    src = DATASETS / "romi_virtual_plant_synthetic"
    if not src.is_dir():
        return None
    truth = {}
    if not ws.images_dir.is_dir():
        ws.images_dir.mkdir(parents=True)
        for p in sorted((src / "images").glob("*_rgb.png")):
            rgba = read_image(p, "rgba")
            cv2.imwrite(str(ws.images_dir / p.name), cv2.cvtColor(rgba[..., :3], cv2.COLOR_RGB2BGR))
    for p in sorted((src / "images").glob("*_rgb.png")):
        truth[p.name] = read_image(src / "images" / p.name.replace("_rgb", "_background"), "gray") < 128
    poses_stage.run(ws, PosesConfig(import_colmap=src / "colmap_text" / "sparse" / "0"))
    try:
        segmentation.run(ws, SegmentConfig())
    except PlantsplatError as exc:  # recorded as the result: the benchmark goes on
        return {"error": str(exc)}
    return score(ws, truth)


def main() -> None:
    from plantsplat.log import setup_logging
    from plantsplat.resources import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[81, 82, 83, 84, 85])
    ap.add_argument("--foreign", nargs="*", default=["101", "102", "103", "104", "108", "110"])
    ap.add_argument("--no-romi", action="store_true")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "plantsplat_bench_poses",
                    help="synthetic captures (shared with bench_poses)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "plantsplat_bench_segment")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--e2e-work", type=Path, default=None,
                    help="score the masks bench_e2e.py's runs left in this folder instead (no segment stage run)")
    args = ap.parse_args()
    os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")
    setup_logging(quiet=True)
    info = machine_info()
    info["loadavg_start"] = list(os.getloadavg())
    rows = kept_runs(args.e2e_work) if args.e2e_work else {}
    if args.e2e_work:
        args.foreign, args.seeds, args.no_romi = [], [], True
        for name, row in rows.items():
            print(name, json.dumps({k: v for k, v in row.items() if k not in ("per_frame", "object")}), flush=True)
    for cap in args.foreign:
        d = DATASETS / "foreign_renders" / cap
        if d.is_dir():
            rows[f"foreign_{cap}"] = foreign(d, Workspace(args.work / f"foreign_{cap}"))
            print(cap, json.dumps({k: v for k, v in rows[f"foreign_{cap}"].items() if k not in ("per_frame", "object")}),
                  flush=True)
        else:
            print(f"foreign capture {d} not found: skipped", flush=True)
    for seed in args.seeds:
        rows[f"synth_{seed}"] = synthetic(seed, args.cache, Workspace(args.work / f"synth_{seed}"))
        print(seed, json.dumps({k: v for k, v in rows[f"synth_{seed}"].items() if k not in ("per_frame", "object")}),
              flush=True)
    romi = None if args.no_romi else romi_virtual(Workspace(args.work / "romi_virtual"))
    if romi:
        print("romi", json.dumps({k: v for k, v in romi.items() if k not in ("per_frame", "object")}), flush=True)
    own = [r["mean_iou"] for k, r in rows.items() if k.startswith(("synth", "demo"))]
    met = {k: {"mean_iou": r["mean_iou"] >= TARGETS["mean_iou_every_capture"],
               "worst_frame": r["worst_iou"] >= TARGETS["worst_frame_iou"],
               "seconds": r["seconds"] <= TARGETS["seconds_120_frames"],
               "far_share": r.get("far_share") is not None and r["far_share"] <= TARGETS["plant_gaussians_far_share"]}
           for k, r in rows.items()}
    summary = {"mean_iou_by_capture": {k: r["mean_iou"] for k, r in rows.items()},
               "worst_iou_by_capture": {k: r["worst_iou"] for k, r in rows.items()},
               "seconds_by_capture": {k: r["seconds"] for k, r in rows.items()},
               "far_share_by_capture": {k: r.get("far_share") for k, r in rows.items()},
               "own_seeds_mean_iou": round(float(np.mean(own)), 4) if own else None}
    info["loadavg_end"] = list(os.getloadavg())
    mode = (f"masks of the bench_e2e.py runs kept in {args.e2e_work} (the segment stage not run again)" if args.e2e_work
            else "frames and poses as a user runs them, then the segment stage")
    write_json_atomic(args.out, {"benchmark": "segment", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                                 "mode": mode,
                                 "machine": info, "targets": TARGETS, "summary": summary, "targets_met": met,
                                 "romi_virtual": romi, "captures": rows})
    print(json.dumps(summary, indent=1))
    if args.work.is_dir() and not any(args.work.iterdir()):
        shutil.rmtree(args.work)


if __name__ == "__main__":
    main()

"""Benchmark of the capture front end: frame extraction speed and mask quality/speed per backend.

1. Frame extraction: a generated 60 s, 30 fps, 1920x1080 H.264 video (portrait rotation tag) ->
   120 frames at 960 px (target: under 30 s).
2. Segmentation on synthetic captures (``plantsplat synth``, several seeds, 540x960): mask IoU
   against the ground truth (mean, worst frame), boundary F-score (2 px tolerance) and seconds per
   frame, for the classic backend (targets: mean IoU >= 0.95, worst >= 0.85, <= 0.1 s per frame) and
   for SAM-2 when ``--sam2-checkpoint`` is given. Without a checkpoint, ``--sam2-random-weights CONFIG`` times
   the sam2 backend with a randomly initialised model of that SAM-2 architecture (its speed does not depend
   on the weights; its masks are meaningless, so no quality is recorded for it).

Writes ``benchmarks/results/segment.json`` (atomically), with machine info (CPU, cores, load, versions).

Usage:
    .venv/bin/python benchmarks/bench_segment.py [--seeds 0 1 2 3 4] [--frames 120] [--skip-video]
    .venv/bin/python benchmarks/bench_segment.py --seeds 0 --skip-video \
        --sam2-random-weights configs/sam2.1/sam2.1_hiera_t.yaml --results benchmarks/results/segment_sam2_speed.json
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from plantsplat.frames import extract_frames
from plantsplat.io import write_json_atomic
from plantsplat.resources import machine_info
from plantsplat.segment import mask_iou, segment_workspace
from plantsplat.segment.sam2_backend import random_checkpoint
from plantsplat.synth.mesh import CALYX, CLASS_NAMES
from plantsplat.workspace import Workspace

RESULTS = Path(__file__).resolve().parent / "results" / "segment.json"


def make_video(path: Path, seconds: float = 60, fps: int = 30, w: int = 1920, h: int = 1080) -> float:
    """A textured scene panning past the camera (changing every frame), H.264, rotation tag -90."""
    import av

    rng = np.random.default_rng(0)
    big = cv2.resize((rng.random((h // 6, (w * 3) // 6, 3)) * 255).astype(np.uint8), (w * 3, h),
                     interpolation=cv2.INTER_CUBIC)
    t = time.perf_counter()
    n = int(seconds * fps)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.options = {"preset": "ultrafast", "crf": "20"}
        s.set_display_rotation(-90)
        for i in range(n):
            x = int(i * (2 * w) / n)
            frame = np.ascontiguousarray(big[:, x:x + w])
            for p in s.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return time.perf_counter() - t


def boundary_f(pred: np.ndarray, gt: np.ndarray, tol: int = 2) -> float:
    """Boundary F-score: boundary pixels of each mask within ``tol`` px of the other's boundary."""
    k = np.ones((3, 3), np.uint8)

    def edge(m):
        m8 = m.astype(np.uint8)
        return m8 - cv2.erode(m8, k)

    bp, bg = edge(pred), edge(gt)
    if bp.sum() == 0 and bg.sum() == 0:
        return 1.0
    if bp.sum() == 0 or bg.sum() == 0:
        return 0.0
    dg = cv2.distanceTransform(1 - bg, cv2.DIST_L2, 3)
    dp = cv2.distanceTransform(1 - bp, cv2.DIST_L2, 3)
    precision = float((dg[bp > 0] <= tol).mean())
    recall = float((dp[bg > 0] <= tol).mean())
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


# the synthetic capture's class ids (``plantsplat synth --class-maps``) grouped into what the errors are told apart by:
# the calyx counts as fruit, the six cube faces as one cube
PART_OF_CLASS = {c: "fruit" if c == CALYX else name.split()[0] for c, name in CLASS_NAMES.items()}


def score_capture(cap: Path, ws: Workspace, frames_info: dict) -> dict:
    """Mask IoU (mean, worst, median), boundary F, and with class maps the errors by part: ``missed_pct`` (foreground
    pixels of each organ or the cube left out) and ``taken_pct`` (background pixels of each part taken), both in % of
    all foreground pixels, and ``recall`` per foreground part. ``errors_on_outline_pct``: the share of wrong pixels
    that lie within a pixel of the true outline; ``mean_iou_off_outline``: IoU with those pixels left out of both."""
    ious, bfs, ious_off, on_outline, n_err = [], [], [], 0, 0
    k3 = np.ones((3, 3), np.uint8)
    missed: dict[str, int] = {}
    taken: dict[str, int] = {}
    total: dict[str, int] = {}
    n_fg = 0
    for f in frames_info["frames"]:
        gt = cv2.imread(str(cap / "masks" / f["source_name"]), cv2.IMREAD_GRAYSCALE) > 127
        m = cv2.imread(str(ws.masks_dir / f["name"]), cv2.IMREAD_GRAYSCALE) > 127
        ious.append(mask_iou(gt, m))
        bfs.append(boundary_f(m, gt))
        # pixels within a pixel of the true outline (either side), where the pixel-centre rule and the frame's
        # anti-aliased, blurred edge disagree by design: how much of the error lies there, and IoU without them
        g8 = gt.astype(np.uint8)
        band = (cv2.dilate(g8, k3) > 0) & ~(cv2.erode(g8, k3) > 0)
        err = gt ^ m
        n_err += int(err.sum())
        on_outline += int((err & band).sum())
        ious_off.append(mask_iou(gt & ~band, m & ~band))
        cls_path = cap / "classes" / f["source_name"]
        if cls_path.is_file():
            ids = cv2.imread(str(cls_path), cv2.IMREAD_UNCHANGED)
            n_fg += int(gt.sum())
            for c in np.unique(ids).tolist():
                sel = ids == c
                name = PART_OF_CLASS.get(c, str(c))
                if gt[sel].all():
                    total[name] = total.get(name, 0) + int(sel.sum())
                    missed[name] = missed.get(name, 0) + int((sel & ~m).sum())
                else:
                    taken[name] = taken.get(name, 0) + int((sel & m).sum())
    ious = np.array(ious)
    out = {"mean_iou": round(float(ious.mean()), 4), "worst_iou": round(float(ious.min()), 4),
           "worst_frame": frames_info["frames"][int(ious.argmin())]["source_name"],
           "median_iou": round(float(np.median(ious)), 4), "boundary_f_2px": round(float(np.mean(bfs)), 4),
           "mean_iou_off_outline": round(float(np.mean(ious_off)), 4),
           "errors_on_outline_pct": round(100.0 * on_outline / max(n_err, 1), 2),
           "per_frame_iou": [round(x, 3) for x in ious.tolist()]}
    if n_fg:
        out["missed_pct"] = {k: round(100.0 * v / n_fg, 3) for k, v in sorted(missed.items(), key=lambda kv: -kv[1])}
        out["taken_pct"] = {k: round(100.0 * v / n_fg, 3) for k, v in sorted(taken.items(), key=lambda kv: -kv[1])}
        out["recall"] = {k: round(1.0 - missed[k] / total[k], 3) for k in missed}
    return out


def mean_by_part(rows: list[dict], key: str) -> dict:
    """Mean over captures of a per-part figure (a part a capture lacks counts as 0 % for missed/taken)."""
    parts = sorted({p for r in rows for p in r.get(key, {})})
    if key == "recall":
        return {p: round(float(np.mean([r[key][p] for r in rows if p in r.get(key, {})])), 3) for p in parts}
    vals = {p: round(float(np.mean([r.get(key, {}).get(p, 0.0) for r in rows])), 3) for p in parts}
    return dict(sorted(vals.items(), key=lambda kv: -kv[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    ap.add_argument("--frames", type=int, default=120, help="frames per synthetic capture")
    ap.add_argument("--width", type=int, default=540)
    ap.add_argument("--height", type=int, default=960)
    ap.add_argument("--skip-video", action="store_true")
    ap.add_argument("--sam2-checkpoint", type=Path, default=None)
    ap.add_argument("--sam2-random-weights", metavar="CONFIG", default=None,
                    help="time the sam2 backend with a random model of this SAM-2 config (speed only)")
    ap.add_argument("--results", type=Path, default=RESULTS, help="where to write the JSON results")
    ap.add_argument("--work", type=Path, default=None, help="keep captures here (default: a temp folder)")
    args = ap.parse_args()
    os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")
    from plantsplat.synth import SynthConfig, generate

    out: dict = {"machine": machine_info(), "targets": {
        "classic_mean_iou": 0.95, "classic_worst_iou": 0.85, "classic_seconds_per_frame_540x960": 0.1,
        "extract_120_of_60s_1080p_seconds": 30.0}}
    with tempfile.TemporaryDirectory(prefix="bench_segment_") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        if not args.skip_video:
            video = work / "video_60s_1080p.mp4"
            enc = make_video(video)
            t, c = time.perf_counter(), time.process_time()
            info = extract_frames(video, Workspace(work / "ws_video"), num=120, max_size=960, force=True)
            dt, dc = time.perf_counter() - t, time.process_time() - c
            out["frame_extraction"] = {"video": "60 s, 30 fps, 1920x1080 H.264 (yuv420p), rotation -90",
                                       "encode_s": round(enc, 2), "extract_s": round(dt, 2),
                                       "extract_cpu_s": round(dc, 2),
                                       "frames_written": len(info["frames"]), "working_size": info["working_size"],
                                       "dropped": len(info["dropped"]), "target_s": 30.0, "met": dt < 30.0,
                                       "loadavg_after": list(os.getloadavg())}
            print(f"frame extraction: {dt:.1f} s for {len(info['frames'])} frames")
        sam2_ckpt, sam2_random = args.sam2_checkpoint, args.sam2_checkpoint is None and bool(args.sam2_random_weights)
        if sam2_random:
            sam2_ckpt = random_checkpoint(args.sam2_random_weights, work / "sam2_random.pt")
        backends = ["classic"] + (["sam2"] if sam2_ckpt else [])
        runs = {b: [] for b in backends}
        for seed in args.seeds:
            cap = work / f"synth_{seed}"
            if not (cap / "ground_truth.json").is_file():
                generate(SynthConfig(out=cap, seed=seed, frames=args.frames, width=args.width, height=args.height,
                                     class_maps=True, force=True))
            for b in backends:
                ws = Workspace(work / f"ws_{seed}_{b}")
                finfo = extract_frames(cap / "frames", ws, num=10_000, blur_ratio=0.0, dup_threshold=-1.0, force=True)
                t, c = time.perf_counter(), time.process_time()
                seg = segment_workspace(ws, backend=b, force=True, sam2_checkpoint=sam2_ckpt,
                                        sam2_config=args.sam2_random_weights if sam2_random else None)
                dt, dc = time.perf_counter() - t, time.process_time() - c
                speed_only = b == "sam2" and sam2_random
                sc = {k: seg["settings"]["sam2"][k] for k in ("device", "image_size")} if speed_only else \
                    score_capture(cap, ws, finfo)
                sc.update(seed=seed, frames=len(finfo["frames"]), seconds_per_frame=round(dt / len(finfo["frames"]), 4),
                          cpu_seconds_per_frame=round(dc / len(finfo["frames"]), 4),
                          locator=seg["capture"].get("plant_locator"),
                          frames_with_cube_pose=seg["capture"].get("frames_with_cube_pose"),
                          excluded=len(seg["excluded"]), loadavg=list(os.getloadavg()))
                runs[b].append(sc)
                if speed_only:
                    print(f"{b} seed {seed} (random weights, speed only): {sc['seconds_per_frame']:.3f} s/frame "
                          f"({sc['cpu_seconds_per_frame']:.3f} CPU s/frame)")
                    continue
                print(f"{b} seed {seed}: mean IoU {sc['mean_iou']:.3f} worst {sc['worst_iou']:.3f} "
                      f"BF {sc['boundary_f_2px']:.3f} {sc['seconds_per_frame']:.3f} s/frame "
                      f"({sc['cpu_seconds_per_frame']:.3f} CPU s/frame)")
        out["segmentation"] = {}
        for b, rs in runs.items():
            if not rs:
                continue
            if b == "sam2" and sam2_random:
                out["segmentation"][b] = {
                    "random_weights": args.sam2_random_weights, "device": rs[0]["device"],
                    "quality": "not measured: a randomly initialised model (speed only; no checkpoint on this machine)",
                    "seconds_per_frame": round(float(np.mean([r["seconds_per_frame"] for r in rs])), 4),
                    "cpu_seconds_per_frame": round(float(np.mean([r["cpu_seconds_per_frame"] for r in rs])), 4),
                    "note": "includes the classic pass that prompts it", "per_seed": rs}
                continue
            agg = {"seeds": args.seeds, "frames_per_capture": args.frames, "size": [args.width, args.height],
                   "mean_iou": round(float(np.mean([r["mean_iou"] for r in rs])), 4),
                   "worst_iou": round(float(np.min([r["worst_iou"] for r in rs])), 4),
                   "boundary_f_2px": round(float(np.mean([r["boundary_f_2px"] for r in rs])), 4),
                   **{k: round(float(np.mean([r[k] for r in rs])), 4)
                      for k in ("mean_iou_off_outline", "errors_on_outline_pct")},
                   "seconds_per_frame": round(float(np.mean([r["seconds_per_frame"] for r in rs])), 4),
                   "cpu_seconds_per_frame": round(float(np.mean([r["cpu_seconds_per_frame"] for r in rs])), 4),
                   **{f"{k}_mean": mean_by_part(rs, k) for k in ("missed_pct", "taken_pct", "recall")
                      if any(k in r for r in rs)},
                   "per_seed": rs}
            if b == "classic":
                agg["met"] = {"mean_iou": agg["mean_iou"] >= 0.95, "worst_iou": agg["worst_iou"] >= 0.85,
                              "seconds_per_frame": agg["seconds_per_frame"] <= 0.1}
            out["segmentation"][b] = agg
        if "sam2" not in out["segmentation"]:
            out["segmentation"]["sam2"] = {"not_run": "no SAM-2 checkpoint on this machine (pass --sam2-checkpoint)"}
    out["machine"]["loadavg_end"] = list(os.getloadavg())
    write_json_atomic(args.results, out)
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()

"""End-to-end benchmark (issue 8): the demo's time per stage, and optionally a batch of synthetic plants
with the paper's accuracy table for object-centric and full-scene reconstructions.

    python benchmarks/bench_e2e.py                          # the demo (120 frames, 540x960) -> results/e2e.json
    python benchmarks/bench_e2e.py --out /tmp/demo          # reuse (resume) a demo folder
    python benchmarks/bench_e2e.py --batch 5 --workers 2    # + 5 synthetic plants, object and full modes
    python benchmarks/bench_e2e.py --skip-demo --batch 5 --num-frames 72 --max-size 640   # the batch part only

Stage times and peak memory come from each workspace's run.json (the run that did the work), so a
resumed demo reports the original timings; the machine and its load are recorded.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

from plantsplat.cli import main as cli
from plantsplat.io import read_json, write_json_atomic
from plantsplat.resources import machine_info

RESULTS = Path(__file__).resolve().parent / "results"


def demo(out: Path) -> dict:
    t0 = time.perf_counter()
    code = cli(["demo", "--out", str(out)])
    run = read_json(out / "workspace" / "run.json")
    evaluation = read_json(out / "workspace" / "evaluation.json") if (out / "workspace" / "evaluation.json").is_file() else None
    stages = {k: {"seconds": v.get("seconds"), "peak_rss_mb": v.get("peak_rss_mb")} for k, v in run["stages"].items()}
    synth = read_json(out / "capture" / "ground_truth.json").get("timings_s", {})
    return {
        "exit_code": code,
        "wall_seconds_this_call": round(time.perf_counter() - t0, 1),
        "stages": stages,
        "pipeline_seconds": run.get("total_seconds"),
        "synth_seconds": synth.get("total_s"),
        "target_seconds": 600,
        "traits_vs_truth": evaluation["traits"] if evaluation else None,
        "image_metrics": _image_metrics(out / "workspace" / "metrics.json"),
        "run_machine": run.get("machine"),
    }


def _image_metrics(f: Path) -> dict | None:
    """The trained model's test-view metrics and training time (the train stage's time includes the evaluation)."""
    if not f.is_file():
        return None
    m = read_json(f)
    return {k: m.get(k) for k in ("composite", "foreground", "n_gaussians", "train_seconds", "train_cpu_seconds",
                                  "iterations", "render_fps", "peak_rss_mb", "n_test_views")}


def _traits(ws: Path) -> dict | None:
    f = ws / "traits.json"
    return read_json(f) if f.is_file() else None


def batch(n: int, workers: int, root: Path, iterations: int | None, num_frames: int, max_size: int,
          modes: tuple[str, ...]) -> dict:
    """``n`` synthetic plants: each run alone (object mode), then as a batch with ``workers`` per mode.

    The single runs give the reference time (their sum over ``workers``) and the traits a batch must
    reproduce; each batch gives its wall time and the accuracy table against the truth.
    """
    import shutil

    from plantsplat.synth import SynthConfig, generate
    from plantsplat.traitdefs import TRAIT_KEYS

    root.mkdir(parents=True, exist_ok=True)
    rows, truth_rows = [], []
    for seed in range(100, 100 + n):
        cap = root / f"capture_{seed}"
        if not (cap / "ground_truth.json").is_file():
            generate(SynthConfig(seed=seed, out=cap, force=True))
        gt = read_json(cap / "ground_truth.json")
        rows.append((f"plant{seed}", str(cap / "video.mp4")))
        truth_rows.append((f"plant{seed}", *[gt[k] for k in TRAIT_KEYS]))
    manifest = root / "plants.csv"
    with manifest.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", "input"])
        w.writerows(rows)
    gt_csv = root / "truth.csv"
    with gt_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", *TRAIT_KEYS])
        w.writerows(truth_rows)
    common = ["--num-frames", str(num_frames), "--max-size", str(max_size)]
    if iterations:
        common += ["--iterations", str(iterations)]
    out: dict = {"plants": n, "workers": workers, "num_frames": num_frames, "max_size": max_size,
                 "iterations": iterations}
    # every plant alone (object mode): the reference for the batch's time and numbers
    single_dir = root / "single"
    shutil.rmtree(single_dir, ignore_errors=True)
    singles = {}
    for pid, video in rows:
        t0 = time.perf_counter()
        code = cli(["run", video, "--out", str(single_dir / pid), *common])
        singles[pid] = {"exit_code": code, "wall_seconds": round(time.perf_counter() - t0, 1),
                        "traits": _traits(single_dir / pid)}
        print(f"single {pid}: exit {code}, {singles[pid]['wall_seconds']} s", flush=True)
    sum_single = sum(v["wall_seconds"] for v in singles.values())
    out["single"] = {"per_plant": singles, "sum_seconds": round(sum_single, 1),
                     "sum_over_workers_seconds": round(sum_single / workers, 1)}
    for mode in modes:
        bdir = root / mode
        shutil.rmtree(bdir, ignore_errors=True)
        args = ["batch", str(manifest), "--out", str(bdir), "--workers", str(workers),
                "--ground-truth", str(gt_csv), "--mode", mode, *common]
        t0 = time.perf_counter()
        code = cli(args)
        wall = time.perf_counter() - t0
        summary = read_json(bdir / "batch.json")
        res = {"exit_code": code, "wall_seconds": round(wall, 1), "n_ok": summary["n_ok"],
               "accuracy": summary.get("accuracy", {}).get("table")}
        if mode == "object":
            res["ratio_to_single_sum_over_workers"] = round(wall / (sum_single / workers), 3)
            res["target_ratio"] = 1.1
            diffs = {}
            for pid, _ in rows:
                a, b = singles[pid]["traits"], _traits(bdir / "plants" / pid)
                if a and b:
                    diffs[pid] = {k: (None if a.get(k) is None or b.get(k) is None else
                                      round(abs(a[k] - b[k]) / max(abs(a[k]), 1e-9) * 100, 3)) for k in TRAIT_KEYS}
            res["traits_diff_vs_single_pct"] = diffs
            vals = [v for d in diffs.values() for v in d.values() if v is not None]
            res["traits_max_diff_vs_single_pct"] = max(vals) if vals else None
        out[mode] = res
        print(f"batch {mode}: exit {code}, {res['wall_seconds']} s", flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("/tmp/plantsplat-bench-demo"))
    ap.add_argument("--batch", type=int, default=0, help="number of synthetic plants for the batch part")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--num-frames", type=int, default=120, help="frames per plant in the batch part")
    ap.add_argument("--max-size", type=int, default=960, help="working image size in the batch part")
    ap.add_argument("--modes", nargs="+", default=["object", "full"], choices=["object", "full"])
    ap.add_argument("--skip-demo", action="store_true", help="keep the demo figures of the last results file")
    ap.add_argument("--results", type=Path, default=RESULTS / "e2e.json")
    args = ap.parse_args()
    previous = read_json(args.results) if args.results.is_file() else {}
    result = {"benchmark": "e2e", "machine": machine_info()}
    result["demo"] = previous.get("demo") if args.skip_demo else demo(args.out)
    if args.batch:
        result["batch"] = batch(args.batch, args.workers, args.out.parent / "plantsplat-bench-batch", args.iterations,
                                args.num_frames, args.max_size, tuple(args.modes))
    elif previous.get("batch"):
        result["batch"] = previous["batch"]
    result["machine_after"] = {"loadavg": machine_info()["loadavg"]}
    write_json_atomic(args.results, result)
    print(f"wrote {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

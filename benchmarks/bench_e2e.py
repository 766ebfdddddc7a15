"""End-to-end benchmark (issue 8): the demo's time per stage, and optionally a batch of synthetic plants
with the paper's accuracy table for object-centric and full-scene reconstructions.

    python benchmarks/bench_e2e.py                          # the demo (120 frames, 540x960) -> results/e2e.json
    python benchmarks/bench_e2e.py --out /tmp/demo          # reuse (resume) a demo folder
    python benchmarks/bench_e2e.py --batch 5 --workers 2    # + 5 synthetic plants, object and full modes

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
        "run_machine": run.get("machine"),
    }


def batch(n: int, workers: int, root: Path, iterations: int | None) -> dict:
    from plantsplat.synth import SynthConfig, generate

    root.mkdir(parents=True, exist_ok=True)
    rows, truth_rows = [], []
    for seed in range(100, 100 + n):
        cap = root / f"capture_{seed}"
        if not (cap / "ground_truth.json").is_file():
            generate(SynthConfig(seed=seed, out=cap, force=True))
        gt = read_json(cap / "ground_truth.json")
        rows.append((f"plant{seed}", str(cap / "video.mp4")))
        truth_rows.append((f"plant{seed}", gt["height_cm"], gt["width1_cm"], gt["width2_cm"]))
    manifest = root / "plants.csv"
    with manifest.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", "input"])
        w.writerows(rows)
    gt_csv = root / "truth.csv"
    with gt_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["plant_id", "height_cm", "width1_cm", "width2_cm"])
        w.writerows(truth_rows)
    out = {}
    for mode in ("object", "full"):
        args = ["batch", str(manifest), "--out", str(root / mode), "--workers", str(workers),
                "--ground-truth", str(gt_csv), "--mode", mode]
        if iterations:
            args += ["--iterations", str(iterations)]
        t0 = time.perf_counter()
        code = cli(args)
        summary = read_json(root / mode / "batch.json")
        out[mode] = {"exit_code": code, "wall_seconds": round(time.perf_counter() - t0, 1),
                     "n_ok": summary["n_ok"], "accuracy": summary.get("accuracy", {}).get("table")}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("/tmp/plantsplat-bench-demo"))
    ap.add_argument("--batch", type=int, default=0, help="number of synthetic plants for the batch part")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=None)
    args = ap.parse_args()
    result = {"benchmark": "e2e", "machine": machine_info(), "demo": demo(args.out)}
    if args.batch:
        result["batch"] = batch(args.batch, args.workers, args.out.parent / "plantsplat-bench-batch", args.iterations)
    result["machine_after"] = {"loadavg": machine_info()["loadavg"]}
    write_json_atomic(RESULTS / "e2e.json", result)
    print(f"wrote {RESULTS / 'e2e.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A stage of this tree against an earlier commit's, in turns on the same inputs: how much a change saved.

The machine's speed drifts by a quarter over a day (the same steps of the same code took 20-30 % longer in one run
of ``bench_poses.py`` than in another), so a time is only compared with a reference measured beside it. The earlier
commit is checked out into a temporary git worktree; each round runs the stage on a fresh copy of the inputs, first
with the reference's source and then with this tree's (each in a process of its own), and records the stage's wall
time. A change made for speed must give the same result, which is compared:

- ``--stage poses`` (``--workspace``: a workspace after ``plantsplat frames``): the steps' times (``poses.json``
  ``timings``) and the cameras;
- ``--stage train`` (a workspace after ``plantsplat segment``): the training loop's seconds (``metrics.json``
  ``train_seconds``; the rest of the wall time is loading the frames and scoring the test views) and the test
  views' metrics. Each tree first runs once untimed: its first run compiles its numba kernels.
- ``--stage run`` (``--source``: a video): ``plantsplat run`` on it into a fresh workspace, every stage's seconds
  (``run.json``) and the traits. With ``--cold`` each run starts with an empty numba cache (``NUMBA_CACHE_DIR``), as
  the first run after an install does; without it each tree first runs once untimed.

Writes ``benchmarks/results/<stage>_ab.json`` with machine information and the date.

Usage:
    .venv/bin/python benchmarks/bench_stage_ab.py --stage poses --ref 0d03586 --workspace WS
    .venv/bin/python benchmarks/bench_stage_ab.py --stage train --ref 9e9de32 --workspace WS
    .venv/bin/python benchmarks/bench_stage_ab.py --stage run --cold --ref 1be0634 --source capture/video.mp4
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from plantsplat.errors import EXIT_RESULT_FAILED

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
TRAIN_INPUTS = ("images", "masks", "sparse", "frames.json", "poses.json", "transforms.json", "markers.json",
                "segment.json", "sparse_points.ply")
"""What the train stage reads of a workspace (copied for each run)."""
METRIC_KEYS = (("composite", "psnr"), ("composite", "ssim"), ("composite", "lpips"), ("foreground", "psnr"),
               ("foreground", "ssim"), ("foreground", "lpips"), ("mask_agreement", "iou"))


def _run(src: Path, args: list[str], env_extra: dict | None = None, ok_codes: tuple[int, ...] = (0,)) -> float:
    """``plantsplat ARGS`` with the package in ``src``, in a process of its own; its wall seconds. Both trees score
    LPIPS with this tree's weights (the reference's worktree is not beside ``../shared``, where they are looked for)."""
    from plantsplat.train.metrics import default_lpips_weights

    weights = default_lpips_weights()
    env = {**os.environ, "PYTHONPATH": str(src), "PLANTSPLAT_NO_PROGRESS": "1",
           **({"PLANTSPLAT_LPIPS_WEIGHTS": str(weights)} if weights else {}), **(env_extra or {})}
    where = subprocess.run([sys.executable, "-c", "import plantsplat; print(plantsplat.__file__)"], env=env,
                           capture_output=True, text=True).stdout.strip()
    if not where.startswith(str(src)):
        raise SystemExit(f"{src}: the package imported from {where} instead")
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "plantsplat", *args], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode not in ok_codes:
        raise SystemExit(f"{src}: plantsplat {args[0]} ended with code {proc.returncode}: {proc.stderr.strip()[-300:]}")
    return wall


def _fresh(work: Path, ws: Path, names: tuple[str, ...]) -> None:
    """``work`` emptied and given a copy of ``names`` from the workspace ``ws`` (those it has)."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    for n in names:
        if (ws / n).is_dir():
            shutil.copytree(ws / n, work / n)
        elif (ws / n).is_file():
            shutil.copy(ws / n, work / n)


def run_poses(src: Path, ws: Path, work: Path) -> dict:
    """``plantsplat poses`` with the package in ``src`` on a copy of ``ws``'s frames: wall time, steps, cameras."""
    _fresh(work, ws, ("images", "frames.json"))
    wall = _run(src, ["poses", str(work)])
    report = json.loads((work / "poses.json").read_text())
    cams = {f["file_path"]: np.asarray(f["transform_matrix"]) for f in
            json.loads((work / "transforms.json").read_text())["frames"]}
    return {"wall_seconds": round(wall, 1), "stage_seconds": report["timings"]["total_s"], "timings": report["timings"],
            "registered": report["registered"], "result": cams}


def run_train(src: Path, ws: Path, work: Path) -> dict:
    """``plantsplat train`` with the package in ``src`` on a copy of ``ws``'s frames, masks and poses: wall time, the
    training loop's seconds, the test views' metrics."""
    _fresh(work, ws, TRAIN_INPUTS)
    wall = _run(src, ["train", str(work)])
    m = json.loads((work / "metrics.json").read_text())
    return {"wall_seconds": round(wall, 1), "stage_seconds": round(wall, 1), "train_seconds": m["train_seconds"],
            "rest_seconds": round(wall - m["train_seconds"], 1), "n_gaussians": m["n_gaussians"],
            "result": {f"{a}.{b}": m[a][b] for a, b in METRIC_KEYS}}


TRAIT_KEYS = ("height_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2")


def run_run(src: Path, source: Path, work: Path, cold: bool) -> dict:
    """``plantsplat run`` with the package in ``src`` on the video ``source`` into an empty workspace (with ``cold``,
    and an empty numba cache): wall time, every stage's seconds, the traits."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    env = {"NUMBA_CACHE_DIR": str(work / "numba_cache")} if cold else None
    # a result marked failed (a capture without the cube: no scale) still ran every stage
    wall = _run(src, ["run", str(source), "--out", str(work / "ws")], env, ok_codes=(0, EXIT_RESULT_FAILED))
    rec = json.loads((work / "ws" / "run.json").read_text())
    traits = json.loads((work / "ws" / "traits.json").read_text())
    return {"wall_seconds": round(wall, 1), "stage_seconds": rec["total_seconds"], "quality": traits["quality"],
            "stages": {k: v.get("seconds") for k, v in rec["stages"].items()},
            "result": {k: traits[k] for k in TRAIT_KEYS}}


def _difference(a: dict, b: dict) -> float | None:
    """The largest difference between two runs' results (cameras' matrix entries, or metrics); None when the poses
    registered different frames, infinite when a metric is missing from one run only."""
    if set(a) != set(b):
        return None
    if any((a[k] is None) != (b[k] is None) for k in a):
        return float("inf")
    return max((float(np.abs(np.asarray(a[k], float) - np.asarray(b[k], float)).max()) for k in a if a[k] is not None),
               default=0.0)


def main() -> None:
    from plantsplat.resources import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", choices=("poses", "train", "run"), required=True)
    ap.add_argument("--ref", required=True, help="the earlier commit (any git revision)")
    ap.add_argument("--workspace", type=Path, default=None,
                    help="poses: a workspace after `plantsplat frames`; train: one after `plantsplat segment`")
    ap.add_argument("--source", type=Path, default=None, help="run: the video")
    ap.add_argument("--cold", action="store_true", help="run: every run with an empty numba cache")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="default benchmarks/results/<stage>_ab.json")
    args = ap.parse_args()
    if (args.stage == "run") != (args.source is not None) or (args.stage != "run") == (args.workspace is None):
        raise SystemExit("--stage run takes --source, the others --workspace")
    if args.stage == "run":
        def run(src, _ws, work):
            return run_run(src, args.source.resolve(), work, args.cold)
    else:
        run = {"poses": run_poses, "train": run_train}[args.stage]
    info = machine_info()
    start = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        ref_tree = Path(tmp) / "ref"
        subprocess.run(["git", "worktree", "add", "--detach", "-f", str(ref_tree), args.ref], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            rows, results = [], {}
            if not (ref_tree / "src" / "plantsplat").is_dir():
                raise SystemExit(f"{args.ref}: no src/plantsplat in that commit")
            if args.stage == "train" or (args.stage == "run" and not args.cold):  # a tree's first run compiles its
                # numba kernels: one run each, not timed
                for label, src in (("ref", ref_tree / "src"), ("this", ROOT / "src")):
                    run(src, args.workspace, Path(tmp) / "runs" / label)
            for k in range(args.rounds):
                for label, src in (("ref", ref_tree / "src"), ("this", ROOT / "src")):
                    r = run(src, args.workspace, Path(tmp) / "runs" / label)
                    results.setdefault(label, r.pop("result"))  # the first round's: every round has the same input
                    rows.append({"round": k, "code": label, **r})
                    print(json.dumps({key: rows[-1][key] for key in ("round", "code", "wall_seconds")}), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(ref_tree)], cwd=ROOT, capture_output=True)
    med = {c: float(np.median([r["stage_seconds"] for r in rows if r["code"] == c])) for c in ("ref", "this")}
    result = {"benchmark": f"{args.stage}_ab", "date": start, "machine": {**info, "loadavg_end": list(os.getloadavg())},
              "ref": args.ref, "this": head.strip() or None, "workspace": str(args.workspace or args.source),
              "cold_numba_cache": args.cold, "runs": rows,
              "results": {c: {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
                          for c, r in results.items()} if args.stage != "poses" else None,
              "summary": {"stage_seconds_median": med, "saved_seconds": round(med["ref"] - med["this"], 1),
                          "largest_difference": _difference(results["ref"], results["this"])}}
    out = args.out or RESULTS / f"{args.stage}_ab.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()

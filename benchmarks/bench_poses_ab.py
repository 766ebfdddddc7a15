"""The poses stage of this tree against an earlier commit's, in turns on the same frames: how much a change saved.

The machine's speed drifts by a quarter over a day (the same steps of the same code took 20-30 % longer in one run
of ``bench_poses.py`` than in another), so a time is only compared with a reference measured beside it. The earlier
commit is checked out into a temporary git worktree; each round runs ``plantsplat poses`` on a fresh copy of the frames,
first with the reference's source and then with this tree's (each in a process of its own), and records the stage's
wall time and its steps (``poses.json``: ``timings``). The two models' cameras are compared: a change made for speed
must give the same cameras.

Writes ``benchmarks/results/poses_ab.json`` with machine information and the date.

Usage:
    .venv/bin/python benchmarks/bench_poses_ab.py --ref 0d03586 --frames WS  # WS: a workspace after `plantsplat frames`
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

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "poses_ab.json"


def run_poses(src: Path, frames_ws: Path, work: Path) -> dict:
    """``plantsplat poses`` with the package in ``src`` on a copy of ``frames_ws``'s frames: wall time, steps, cameras."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    shutil.copytree(frames_ws / "images", work / "images")
    shutil.copy(frames_ws / "frames.json", work / "frames.json")
    env = {**os.environ, "PYTHONPATH": str(src), "PLANTSPLAT_NO_PROGRESS": "1"}
    t = time.perf_counter()
    where = subprocess.run([sys.executable, "-c", "import plantsplat; print(plantsplat.__file__)"], env=env,
                           capture_output=True, text=True).stdout.strip()
    if not where.startswith(str(src)):
        raise SystemExit(f"{src}: the package imported from {where} instead")
    proc = subprocess.run([sys.executable, "-m", "plantsplat", "poses", str(work)], env=env, capture_output=True,
                          text=True)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{src}: plantsplat poses ended with code {proc.returncode}: {proc.stderr.strip()[-300:]}")
    report = json.loads((work / "poses.json").read_text())
    cams = {f["file_path"]: np.asarray(f["transform_matrix"]) for f in
            json.loads((work / "transforms.json").read_text())["frames"]}
    return {"wall_seconds": round(wall, 1), "timings": report["timings"], "registered": report["registered"],
            "cameras": cams}


def main() -> None:
    from plantsplat.resources import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", required=True, help="the earlier commit (any git revision)")
    ap.add_argument("--frames", type=Path, required=True, help="a workspace holding images/ and frames.json")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    info = machine_info()
    start = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        ref_tree = Path(tmp) / "ref"
        subprocess.run(["git", "worktree", "add", "--detach", "-f", str(ref_tree), args.ref], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            rows, cams = [], {}
            if not (ref_tree / "src" / "plantsplat").is_dir():
                raise SystemExit(f"{args.ref}: no src/plantsplat in that commit")
            for k in range(args.rounds):
                for label, src in (("ref", ref_tree / "src"), ("this", ROOT / "src")):
                    r = run_poses(src, args.frames, Path(tmp) / "runs" / label)
                    cams.setdefault(label, r.pop("cameras"))  # the first round's: every round maps the same frames
                    rows.append({"round": k, "code": label, **r})
                    print(json.dumps({key: rows[-1][key] for key in ("round", "code", "wall_seconds")}), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(ref_tree)], cwd=ROOT, capture_output=True)
    ref_cams, this_cams = cams["ref"], cams["this"]
    same = set(ref_cams) == set(this_cams)
    diff = max(float(np.abs(ref_cams[n] - this_cams[n]).max()) for n in ref_cams) if same else None
    med = {c: float(np.median([r["timings"]["total_s"] for r in rows if r["code"] == c])) for c in ("ref", "this")}
    result = {"benchmark": "poses_ab", "date": start, "machine": {**info, "loadavg_end": list(os.getloadavg())},
              "ref": args.ref, "this": head.strip() or None, "frames": str(args.frames), "runs": rows,
              "summary": {"stage_seconds_median": med, "saved_seconds": round(med["ref"] - med["this"], 1),
                          "same_frames_registered": same, "camera_max_difference": diff}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()

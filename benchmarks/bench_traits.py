"""Benchmark of `plantsplat traits` over synthetic plants, in the paper's table format.

For each seed, `plantsplat synth` builds a plant + cube scene and its exact ground truth
(``scene_gt.ply``: dense surface samples of the plant and the cube's five visible faces;
``ground_truth.json``). The trait measurement is run on four versions of that cloud:

* ``gt``: the cloud as it is (cm, z up: the calibrated frame);
* ``gt_unscaled``: moved by a random similarity (rotation, scale 0.02..5, translation), measured
  with ``calibrated=False``: the cube alone gives scale, ground and up;
* ``noisy``: 1.5 mm isotropic noise on every point, 2 % of the points dropped, 300 floaters
  (uniform in the box around the scene, away from it) and 4 small floater blobs;
* ``noisy_unscaled``: both.

Full reconstructions (synth -> frames -> segment -> poses -> train -> export) are not part of this
benchmark: training a splat per plant takes far longer than this CPU machine allows.

Usage::

    .venv/bin/python benchmarks/bench_traits.py --plants 12
    # -> benchmarks/results/traits.json and benchmarks/results/traits_scatter_<variant>.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

TRAITS = ("height_cm", "width1_cm", "width2_cm", "canopy_volume_cm3", "canopy_area_cm2", "fruit_count")


def machine_info() -> dict:
    import scipy

    from plantsplat.resources import machine_info as common

    return {**common(), "loadavg_start": os.getloadavg(), "scipy": scipy.__version__}


def synth_scene(seed: int, work: Path) -> tuple[dict, dict]:
    """Ground-truth scene cloud and ground_truth.json of synth seed ``seed`` (tiny render, GT is exact)."""
    from plantsplat.ply import read_point_cloud as read_ply
    from plantsplat.synth import SynthConfig, generate

    out = work / f"seed_{seed:03d}"
    if not (out / "ground_truth.json").is_file():
        generate(SynthConfig(out=out, seed=seed, frames=3, width=64, height=112, msaa=1, force=True))
    gt = json.loads((out / "ground_truth.json").read_text())
    return read_ply(out / "scene_gt.ply"), gt


def degrade(xyz: np.ndarray, rgb: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruction-like damage: noise, dropped points, floaters (far from the surface)."""
    from scipy.spatial import cKDTree

    keep = rng.random(len(xyz)) > 0.02
    p = xyz[keep] + rng.normal(0, 0.15, (int(keep.sum()), 3))
    c = rgb[keep]
    lo, hi = xyz.min(0) - 10, xyz.max(0) + 10
    fl = rng.uniform(lo, hi, (3000, 3))
    d, _ = cKDTree(xyz).query(fl)
    fl = fl[d > 3.0][:300]
    blobs = [rng.normal(rng.uniform(lo, hi), 0.3, (12, 3)) for _ in range(4)]
    blobs = [b for b in blobs if cKDTree(xyz).query(b)[0].min() > 3.0]
    extra = np.concatenate([fl, *blobs]) if blobs else fl
    p = np.concatenate([p, extra])
    c = np.concatenate([c, rng.integers(0, 256, (len(extra), 3)).astype(np.uint8)])
    return p, c


def random_similarity(rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    s = float(np.exp(rng.uniform(np.log(0.02), np.log(5.0))))
    t = rng.uniform(-50, 50, 3) * s
    return R, s, t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", type=int, default=12, help="number of synthetic plants (seeds 0..N-1)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "traits.json")
    ap.add_argument("--work", type=Path, default=None, help="folder for the synth scenes (default: a temp dir)")
    args = ap.parse_args()
    os.environ.setdefault("PLANTSPLAT_NO_PROGRESS", "1")

    from plantsplat.io import write_json_atomic
    from plantsplat.log import setup_logging
    from plantsplat.traits.config import TraitsConfig
    from plantsplat.traits.measure import measure_traits
    from plantsplat.traits.stats import accuracy_table, format_table, scatter_plots

    setup_logging(quiet=True)
    info = machine_info()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_traits_"))
    variants = ("gt", "gt_unscaled", "noisy", "noisy_unscaled")
    est: dict[str, dict[str, dict]] = {v: {} for v in variants}
    robust: dict[str, dict[str, dict]] = {v: {} for v in variants}
    truth: dict[str, dict] = {}
    per_plant = []
    synth_s = 0.0
    for seed in range(args.plants):
        t0 = time.perf_counter()
        scene, gt = synth_scene(seed, work)
        synth_s += time.perf_counter() - t0
        pid = f"seed_{seed:03d}"
        ripe = sum(bool(f.get("ripe", True)) for f in gt.get("plant", {}).get("fruits", []))
        truth[pid] = {k: gt[k] for k in TRAITS} | {"ripe_fruit_count": ripe}
        rng = np.random.default_rng(1000 + seed)
        xyz, rgb = scene["xyz"], scene["rgb"]
        nxyz, nrgb = degrade(xyz, rgb, rng)
        row = {"plant": pid, "points": int(len(xyz)), "truth": truth[pid]}
        for v in variants:
            p, c = (xyz, rgb) if v.startswith("gt") else (nxyz, nrgb)
            calibrated = not v.endswith("unscaled")
            if not calibrated:
                R, s, t = random_similarity(rng)
                p = (p @ R.T) * s + t
            t1 = time.perf_counter()
            res = measure_traits(p, c, calibrated=calibrated)
            dt = time.perf_counter() - t1
            e = {k: res.traits.get(k) for k in TRAITS}
            e["ripe_fruit_count"] = e["fruit_count"]
            est[v][pid] = e
            robust[v][pid] = dict(res.robust)
            row[v] = {"traits": e, "quality": res.quality, "reasons": res.reasons, "seconds": dt,
                      "scale": {k: res.scale.get(k) for k in ("source", "scale", "aruco_vs_planes_pct",
                                                               "cube_edge_cm_planes", "up_method")}}
            if not calibrated:
                row[v]["scale_error_pct"] = (res.scale["scale"] * s - 1) * 100 if res.scale.get("scale") else None
            errs = " ".join(
                f"{k.split('_')[0]}={100 * (e[k] - truth[pid][k]) / truth[pid][k]:+.2f}%"
                for k in TRAITS[:5] if e[k] is not None
            )
            print(f"{pid} {v:15s} {res.quality:8s} {dt:5.1f}s {errs} fruit {e['fruit_count']}/{truth[pid]['fruit_count']}"
                  f" (ripe {ripe})", flush=True)
        per_plant.append(row)
    keys = [*TRAITS, "ripe_fruit_count"]
    tables = {v: accuracy_table(est[v], truth, keys) for v in variants}
    robust_keys = ["height_cm", "width1_cm", "width2_cm"]
    robust_tables = {v: accuracy_table(robust[v], truth, robust_keys) for v in variants}
    res_dir = args.out.parent
    for v in variants:
        scatter_plots(est[v], truth, ["height_cm", "width1_cm", "width2_cm"], res_dir / f"traits_scatter_{v}.png",
                      title=f"plantsplat traits on synthetic plants ({v}, n = {args.plants})")
    targets = {"every trait within 1 % of truth on ground-truth clouds": all(
        abs(r["gt"]["traits"][k] - r["truth"][k]) <= 0.01 * abs(r["truth"][k])
        for r in per_plant for k in TRAITS[:5] if r["gt"]["traits"][k] is not None
    ) and all(r["gt"]["traits"]["height_cm"] is not None for r in per_plant)}
    seconds = {v: float(np.mean([r[v]["seconds"] for r in per_plant])) for v in variants}
    out = {
        "benchmark": "traits",
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": info | {"loadavg_end": os.getloadavg()},
        "plants": args.plants,
        "variants": {
            "gt": "scene_gt.ply (plant + cube ground-truth samples), calibrated frame",
            "gt_unscaled": "same, random rotation/scale(0.02..5)/translation, scale+up from the cube",
            "noisy": "1.5 mm noise, 2 % dropped, ~300 floaters + blobs, calibrated",
            "noisy_unscaled": "noisy + random similarity",
        },
        "reconstructions": "not run: training one splat per plant is beyond this CPU-only benchmark",
        "tables": tables,
        "tables_markdown": {v: format_table({k: tables[v][k] for k in keys}) for v in variants},
        "robust_trim": TraitsConfig().trim,
        "robust_tables": robust_tables,
        "robust_tables_markdown": {v: format_table(robust_tables[v]) for v in variants},
        "mean_seconds_per_plant": seconds,
        "synth_seconds_total": synth_s,
        "targets_met": targets,
        "per_plant": per_plant,
    }
    write_json_atomic(args.out, out)
    for v in variants:
        print(f"\n### {v}  (mean {seconds[v]:.2f} s per plant)\n")
        print(out["tables_markdown"][v])
        print(f"robust (trimmed {TraitsConfig().trim}) height/widths:\n")
        print(out["robust_tables_markdown"][v])
    print(json.dumps(targets))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

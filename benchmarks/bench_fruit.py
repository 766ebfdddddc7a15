"""Benchmark of the fruit count on trained workspaces: each fruit counted against the true fruit.

For each workspace (one that `plantsplat run`, or the stages up to `export`, made from a capture with a ground
truth: a synthetic capture's or a foreign render's ``ground_truth.json``), the traits stage is run twice, with the
frames' check of fruit pieces (``--fruit-views``, the default) and without, and each counted fruit's centre is
matched with the nearest true fruit (within 0.75 of its length plus 1 cm): ``duplicates`` are fruit counted twice
or more, ``missed`` ripe fruit with no count, ``unripe`` unripe fruit counted, ``stray`` counts near no fruit. The
traits stage writes ``traits.json`` as it runs: the workspaces are left with the default's.

Usage::

    .venv/bin/python benchmarks/bench_fruit.py WS1 CAPTURE1 WS2 CAPTURE2 ... --out benchmarks/results/fruit.json

where each ``CAPTURE`` is the folder with the capture's ``ground_truth.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))


def true_fruits(capture: Path) -> list[dict]:
    """Each true fruit: its centre in the cube frame (cm), length and ripeness (both ground-truth layouts)."""
    from plantsplat.poses.evaluate import cube_from_world

    gt = json.loads((capture / "ground_truth.json").read_text())
    T = cube_from_world(gt)
    out = []
    for f in gt["plant"]["fruits"]:
        a, b = np.array(f.get("attach", f.get("calyx_cm"))), np.array(f.get("tip", f.get("tip_cm")))
        c = (a + b) / 2
        out.append({"centre": T[:3, :3] @ c + T[:3, 3], "length": float(np.linalg.norm(b - a)),
                    "ripe": bool(f.get("ripe", True))})
    return out


def assess(centres: list, fruits: list[dict]) -> dict:
    """Counted centres against the true fruit (see the module's docstring)."""
    C = np.array([f["centre"] for f in fruits]).reshape(-1, 3)
    hits: dict[int, int] = {}
    stray = 0
    for p in np.asarray(centres, float).reshape(-1, 3):
        d = np.linalg.norm(C - p, axis=1)
        j = int(np.argmin(d)) if len(d) else -1
        if j < 0 or d[j] > 0.75 * fruits[j]["length"] + 1.0:
            stray += 1
        else:
            hits[j] = hits.get(j, 0) + 1
    ripe = [j for j, f in enumerate(fruits) if f["ripe"]]
    return {"count": len(np.asarray(centres).reshape(-1, 3)), "truth": len(ripe),
            "duplicates": sum(v - 1 for v in hits.values()), "missed": sum(1 for j in ripe if j not in hits),
            "unripe": sum(1 for j in hits if not fruits[j]["ripe"]), "stray": stray}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", help="workspace and capture folder, in turn")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "fruit.json")
    args = ap.parse_args()
    if len(args.pairs) % 2:
        ap.error("give a capture folder after each workspace")
    from plantsplat.resources import machine_info
    from plantsplat.traits import stage
    from plantsplat.traits.config import TraitsConfig

    rows = []
    for ws, cap in zip(args.pairs[::2], args.pairs[1::2]):
        fruits = true_fruits(Path(cap))
        row = {"workspace": ws, "capture": cap}
        for key, views in (("without_views", False), ("with_views", True)):
            t0 = time.perf_counter()
            out = stage.run(ws, TraitsConfig(fruit_views=views), figure=False)
            row[key] = {**assess(out.get("fruit_centres_cm") or [], fruits), "seconds": round(time.perf_counter() - t0, 2)}
        row["pairs"] = (out.get("fruit_pieces") or {}).get("pairs", [])
        rows.append(row)
        print(ws, row["without_views"], row["with_views"], flush=True)
    err = {k: int(sum(abs(r[k]["count"] - r[k]["truth"]) for r in rows)) for k in ("without_views", "with_views")}
    result = {"benchmark": "fruit", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": machine_info(), "count_error_sum": err, "runs": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print("sum of |count - truth|:", err)


if __name__ == "__main__":
    main()

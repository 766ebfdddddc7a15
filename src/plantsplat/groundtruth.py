"""Reading measured (or synthetic) ground-truth traits, and comparing estimates with them.

Two formats are accepted:

* a ``ground_truth.json`` written by ``plantsplat synth`` (one plant);
* a CSV with a ``plant_id`` column and any of the trait columns of :data:`plantsplat.traitdefs.TRAIT_KEYS`
  (``height_cm, width1_cm, width2_cm, canopy_volume_cm3, canopy_area_cm2, fruit_count``); empty cells
  mean "not measured".

Usage:
    rows, problems = read_ground_truth_csv("measured.csv")
    rows["plant_01"]["height_cm"]
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from plantsplat.errors import PlantsplatError
from plantsplat.io import read_json
from plantsplat.traitdefs import TRAIT_KEYS


def read_ground_truth_csv(path: str | Path) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Read a ground-truth CSV: ``({plant_id: {trait: value}}, [problems])``.

    Bad rows (no id, duplicate id, a value that is not a number) are left out and described in
    ``problems``; a file that cannot be read, or has no ``plant_id`` column, raises.
    """
    path = Path(path)
    if not path.is_file():
        raise PlantsplatError(f"{path}: ground-truth file not found")
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PlantsplatError(f"{path}: unreadable CSV ({exc})") from exc
    if "plant_id" not in header:
        raise PlantsplatError(f"{path}: needs a 'plant_id' column (and trait columns such as height_cm)")
    traits = [t for t in TRAIT_KEYS if t in header]
    if not traits:
        raise PlantsplatError(f"{path}: no trait columns; expected some of {', '.join(TRAIT_KEYS)}")
    out: dict[str, dict[str, float]] = {}
    problems: list[str] = []
    for lineno, raw in enumerate(rows, start=2):
        row = {(k or "").strip(): (v or "").strip() for k, v in raw.items()}
        pid = row.get("plant_id", "")
        if not pid:
            problems.append(f"{path}:{lineno}: no plant_id")
            continue
        if pid in out:
            problems.append(f"{path}:{lineno}: duplicate plant_id {pid!r} (first row kept)")
            continue
        values: dict[str, float] = {}
        bad = None
        for t in traits:
            cell = row.get(t, "")
            if cell == "":
                continue
            try:
                v = float(cell)
            except ValueError:
                bad = f"{t}={cell!r} is not a number"
                break
            if not math.isfinite(v) or v < 0:
                bad = f"{t}={cell!r} is not a finite non-negative number"
                break
            values[t] = v
        if bad:
            problems.append(f"{path}:{lineno}: plant {pid!r}: {bad}")
            continue
        out[pid] = values
    return out, problems


def load_ground_truth(path: str | Path, plant_id: str | None = None) -> dict[str, float]:
    """Ground-truth traits of one plant from a synth ``ground_truth.json``, a rendered capture's (``plant`` with
    ``height_above_soil_cm``, as in ``../shared/datasets/foreign_renders``) or a CSV row."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        data = read_json(path)
        if isinstance(data.get("plant"), dict) and "height_above_soil_cm" in data["plant"]:
            data = _rendered_plant_truth(data["plant"])
        values = {k: float(data[k]) for k in TRAIT_KEYS if k in data and data[k] is not None}
        if not values:
            raise PlantsplatError(f"{path}: no trait values ({', '.join(TRAIT_KEYS)}) in this JSON")
        return values
    rows, problems = read_ground_truth_csv(path)
    if plant_id is None:
        if len(rows) != 1:
            raise PlantsplatError(f"{path}: holds {len(rows)} plants; pass --plant-id to choose one")
        return next(iter(rows.values()))
    if plant_id not in rows:
        why = next((p for p in problems if repr(plant_id) in p), None)
        raise PlantsplatError(f"{path}: no usable row for plant {plant_id!r}" + (f" ({why})" if why else ""))
    return rows[plant_id]


def _rendered_plant_truth(plant: dict) -> dict:
    """The traits of the foreign renders' ``ground_truth.json`` (``plant``) under plantsplat's definitions: height
    above the soil; the extent, widths, volume and area over every plant vertex (fruit below the rim too)."""
    every = plant.get("including_parts_below_soil") or plant
    return {"height_cm": plant["height_above_soil_cm"], "height_extent_cm": every.get("height_cm"),
            "width1_cm": every.get("width1_cm"), "width2_cm": every.get("width2_cm"),
            "canopy_volume_cm3": every.get("canopy_volume_cm3"), "canopy_area_cm2": every.get("projected_canopy_area_cm2"),
            "fruit_count": plant.get("n_fruits")}


def compare_traits(estimate: dict, truth: dict[str, float]) -> dict[str, dict]:
    """Per trait: estimate, truth, error (estimate - truth), absolute and percentage error."""
    out = {}
    for key, t in truth.items():
        e = estimate.get(key)
        if e is None or not isinstance(e, (int, float)) or not math.isfinite(float(e)):
            out[key] = {"estimate": None, "truth": t, "error": None, "abs_error": None, "pct_error": None}
            continue
        err = float(e) - t
        out[key] = {
            "estimate": float(e),
            "truth": t,
            "error": err,
            "abs_error": abs(err),
            "pct_error": (abs(err) / abs(t) * 100.0) if t != 0 else None,
        }
    return out

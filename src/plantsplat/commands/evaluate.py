"""`plantsplat evaluate`: one plant's traits against measured (or synthetic) ground truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import tyro

from plantsplat.commands import Command
from plantsplat.pipeline import evaluate_stage, summarize_workspace
from plantsplat.summary import print_summary
from plantsplat.workspace import Workspace


@dataclass
class EvaluateCommand:
    """Compare WS/traits.json with ground truth and write WS/evaluation.json.

    Example: plantsplat evaluate ws/plant01 --ground-truth measured.csv --plant-id plant01
    """

    ws: tyro.conf.Positional[Path]
    """Workspace with traits.json (from `plantsplat traits` or `plantsplat run`)."""
    ground_truth: Path
    """A synth ground_truth.json, or a CSV with plant_id and trait columns (height_cm, width1_cm, ...)."""
    plant_id: str | None = None
    """Row of the CSV to use (default: the workspace folder name)."""


def run(cfg: EvaluateCommand) -> int:
    ws = Workspace(cfg.ws, must_exist=True)
    plant_id = cfg.plant_id
    if plant_id is None and cfg.ground_truth.suffix.lower() == ".csv":
        plant_id = ws.root.name
    result = evaluate_stage(ws, cfg.ground_truth, plant_id, force=True)
    summary = summarize_workspace(ws)
    summary.pop("metrics", None)
    summary.pop("run", None)
    print_summary(summary, result["traits"])
    return 0


COMMAND = Command(
    name="evaluate", config=EvaluateCommand, run=run, help="Compare one plant's traits with ground truth.", order=58
)

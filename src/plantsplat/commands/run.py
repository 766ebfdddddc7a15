"""`plantsplat run`: the whole pipeline for one plant, resumable."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from plantsplat.commands import Command
from plantsplat.pipeline import RunOptions


@dataclass
class RunConfig:
    """Frames, masks, poses, training, export, traits (and evaluation, report) in one go.

    Each stage is skipped when its outputs are up to date, so an interrupted run resumes where it
    stopped. Example: plantsplat run plant01.mov --out ws/plant01
    """

    input: tyro.conf.Positional[Path]
    """Video (mp4/mov) or folder of images of one plant."""
    out: Path
    """Workspace folder for this plant (created if missing; re-running resumes)."""
    ground_truth: Path | None = None
    """Ground truth to evaluate against: a synth ground_truth.json or a CSV (plant_id + trait columns)."""
    plant_id: str | None = None
    """Row of a ground-truth CSV (default: the workspace folder name)."""
    options: RunOptions = field(default_factory=RunOptions)


def run(cfg: RunConfig) -> int:
    from plantsplat.pipeline import run_pipeline
    from plantsplat.summary import print_summary

    cfg.options.ground_truth = cfg.ground_truth
    cfg.options.plant_id = cfg.plant_id
    summary = run_pipeline(cfg.input, cfg.out, cfg.options)
    evaluation = (summary.get("evaluation") or {}).get("traits")
    print_summary(summary, evaluation)
    return 0


COMMAND = Command(name="run", config=RunConfig, run=run, help="The whole pipeline for one plant.", order=70)

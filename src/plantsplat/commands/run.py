"""`plantsplat run`: the whole pipeline for one plant, resumable."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.errors import EXIT_RESULT_FAILED
from plantsplat.pipeline import RunConfig, run_pipeline
from plantsplat.summary import print_summary


@dataclass
class RunCommand:
    """Frames, poses, masks, training, export, traits (and evaluation, report) in one go.

    A stage runs again only when its options, its inputs or its outputs changed since it last
    succeeded, so an interrupted run resumes where it stopped and a failed stage is never built on. Exits with code 4
    when the traits failed their checks (every file is written; traits.json
    says which check). Example: plantsplat run plant01.mov --out ws/plant01
    """

    input: tyro.conf.Positional[Path]
    """Video (mp4/mov) or folder of images of one plant."""
    out: Path
    """Workspace folder for this plant (created if missing; re-running resumes)."""
    ground_truth: Path | None = None
    """Ground truth to evaluate against: a synth ground_truth.json or a CSV (plant_id + trait columns)."""
    plant_id: str | None = None
    """Row of a ground-truth CSV (default: the workspace folder name)."""
    force: bool = False
    """Run every stage again, even those that are up to date."""
    options: Annotated[RunConfig, tyro.conf.arg(name="")] = field(default_factory=RunConfig)


def run(cfg: RunCommand) -> int:
    cfg.options.ground_truth = cfg.ground_truth
    cfg.options.plant_id = cfg.plant_id
    summary = run_pipeline(cfg.input, cfg.out, cfg.options, cfg.force)
    evaluation = (summary.get("evaluation") or {}).get("traits")
    print_summary(summary, evaluation)
    return EXIT_RESULT_FAILED if (summary.get("traits") or {}).get("quality") == "failed" else 0


COMMAND = Command(name="run", config=RunCommand, run=run, help="The whole pipeline for one plant.", order=70)

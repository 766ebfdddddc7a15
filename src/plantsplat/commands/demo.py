"""`plantsplat demo`: render the built-in synthetic capture, run the whole pipeline, compare with the truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from plantsplat.commands import Command
from plantsplat.errors import EXIT_RESULT_FAILED, PlantsplatError
from plantsplat.io import read_json
from plantsplat.log import console, get_logger
from plantsplat.pipeline import RunConfig, run_pipeline, start_kernel_warmup
from plantsplat.summary import print_summary
from plantsplat.synth import SynthConfig, generate

DEMO_SEED = 2025
"""Seed of the built-in sample capture."""


@dataclass
class DemoCommand:
    """Render the built-in synthetic strawberry capture (a phone video with a 10 cm ArUco cube), run the
    whole pipeline on its video, and print the estimated traits next to the exact ground truth.

    Re-running resumes. Example: plantsplat demo --out plantsplat-demo
    """

    out: Path = Path("plantsplat-demo")
    """Folder for the capture (OUT/capture) and the workspace (OUT/workspace)."""
    capture_seed: int = DEMO_SEED
    """Seed of the synthetic plant and scene (the built-in sample is the default)."""
    capture_frames: int = 120
    """Video frames to render."""
    capture_width: int = 540
    """Video width in pixels (portrait)."""
    capture_height: int = 960
    """Video height in pixels."""
    options: Annotated[RunConfig, tyro.conf.arg(name="")] = field(default_factory=RunConfig)


def run(cfg: DemoCommand) -> int:
    log = get_logger("demo")
    capture = cfg.out / "capture"
    gt_path = capture / "ground_truth.json"
    wanted = {"seed": cfg.capture_seed, "frames": cfg.capture_frames, "width": cfg.capture_width,
              "height": cfg.capture_height}
    reuse = False
    if gt_path.is_file() and (capture / "video.mp4").is_file():
        gt = read_json(gt_path)
        have = {"seed": gt.get("seed"), "frames": len(gt.get("frames", [])),
                "width": gt.get("intrinsics", {}).get("width"), "height": gt.get("intrinsics", {}).get("height")}
        reuse = have == wanted
    if reuse:
        log.info("capture %s already rendered, reused", capture)
    else:
        if capture.exists() and any(capture.iterdir()):
            raise PlantsplatError(
                f"{capture}: holds a different capture; choose another --out or delete that folder", exit_code=2
            )
        start_kernel_warmup()  # the training's kernels compile beside the rendering
        log.info("rendering the sample capture (seed %d, %d frames, %dx%d)", cfg.capture_seed, cfg.capture_frames,
                 cfg.capture_width, cfg.capture_height)
        generate(SynthConfig(seed=cfg.capture_seed, out=capture, frames=cfg.capture_frames, width=cfg.capture_width,
                             height=cfg.capture_height))
    opts = cfg.options
    opts.ground_truth = gt_path
    summary = run_pipeline(capture / "video.mp4", cfg.out / "workspace", opts)
    console.rule("plantsplat demo: estimate vs ground truth")
    print_summary(summary, (summary.get("evaluation") or {}).get("traits"))
    return EXIT_RESULT_FAILED if (summary.get("traits") or {}).get("quality") == "failed" else 0


COMMAND = Command(
    name="demo",
    config=DemoCommand,
    run=run,
    help="Render the sample capture, run everything, compare with the truth.",
    order=75,
)

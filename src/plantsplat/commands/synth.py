"""`plantsplat synth`: render a synthetic phone capture of a potted strawberry with exact ground truth."""

from __future__ import annotations

from plantsplat.commands import Command
from plantsplat.synth import SynthConfig, generate


def run(cfg: SynthConfig) -> int:
    info = generate(cfg)
    t = info["traits"]
    print(f"{info['out']}: {info['frames']} frames in {info['timings']['total_s']:.1f} s; ground truth: height "
          f"{t['height_cm']:.1f} cm, width1 {t['width1_cm']:.1f} cm, width2 {t['width2_cm']:.1f} cm, "
          f"{t['fruit_count']} fruits")
    return 0


COMMAND = Command(
    name="synth",
    config=SynthConfig,
    run=run,
    help="Render a synthetic phone capture of a potted strawberry (video, frames, masks, exact ground truth).",
    order=10,
)

"""Option values checked before a stage runs, so that a bad value changes no stage record.

Each stage's options have rules here (a value a stage cannot work with: a cube of 0 cm, an opacity
of 2, a NaN ratio, a run of 10^20 steps). :func:`check_options` raises a one-line
:class:`~plantsplat.errors.UsageError` (exit code 2) naming the option as the user typed it:
``--cube-size`` for ``plantsplat poses``, ``--poses.cube-size`` for ``plantsplat run`` (``prefix``).

Example:
    >>> from plantsplat.frames import FramesConfig
    >>> check_options(FramesConfig(), "frames")
    >>> check_options(FramesConfig(blur_ratio=float("nan")), "frames", prefix="frames.")
    Traceback (most recent call last):
    ...
    plantsplat.errors.UsageError: --frames.blur-ratio nan: must be a number from 0 to 1
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from plantsplat.errors import UsageError

MAX_ITERATIONS = 1_000_000
"""Training steps a run may ask for (the paper trains 30,000)."""


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def positive(v: Any) -> bool:
    return _number(v) and v > 0


def non_negative(v: Any) -> bool:
    return _number(v) and v >= 0


def share(v: Any) -> bool:
    return _number(v) and 0 <= v <= 1


def optional(rule: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: v is None or rule(v)


def at_least(low: float, high: float = math.inf) -> Callable[[Any], bool]:
    return lambda v: _number(v) and low <= v <= high


# stage -> [(field, rule, what the value must be)]
RULES: dict[str, list[tuple[str, Callable[[Any], bool], str]]] = {
    "frames": [("num", at_least(1), "at least 1"), ("max_size", at_least(16), "at least 16 (px)"),
               ("min_frames", at_least(1), "at least 1"), ("blur_ratio", share, "a number from 0 to 1"),
               ("dup_threshold", at_least(0, 255), "a number from 0 to 255")],
    "poses": [("cube_size", positive, "a number above 0 (cm)"), ("marker_size", positive, "a number above 0 (cm)"),
              ("max_residual_px", positive, "a number above 0 (px)"), ("num_threads", at_least(1), "at least 1"),
              ("ba_loss_px", positive, "a number above 0 (px)"),
              ("max_off_path_block", share, "a number from 0 to 1"),
              ("mapper_switch_sigma", non_negative, "a number of at least 0")],
    "segment": [("scene_resolution", at_least(16), "at least 16 (px)"), ("scene_steps", at_least(1), "at least 1"),
                ("refine_band_px", at_least(0), "0 or more (px)"), ("max_excluded", share, "a number from 0 to 1"),
                ("min_plant_fraction", share, "a number from 0 to 1")],
    "train": [("iterations", optional(at_least(1, MAX_ITERATIONS)), f"from 1 to {MAX_ITERATIONS:,}"),
              ("init_points", at_least(1, 100_000_000), "from 1 to 100,000,000"),
              ("checkpoint_seconds", non_negative, "0 or more (seconds)"), ("threads", at_least(0), "0 or more"),
              ("max_resolution", optional(at_least(0)), "0 or more (px)"),
              ("max_gaussians", optional(at_least(0)), "0 or more")],
    "export": [("min_opacity", at_least(0, 0.999), "a number from 0 to below 1")],
    "traits": [("trim", at_least(0, 0.499), "a number from 0 to below 0.5"), ("eps", optional(positive), "above 0"),
               ("min_points", at_least(1), "at least 1"), ("merge_distance_cm", optional(non_negative), "0 or more"),
               ("cube_size_cm", optional(positive), "a number above 0 (cm)"), ("opacity_min", share, "from 0 to 1"),
               ("extent_sigma", at_least(0, 10), "a number from 0 to 10")],
}


def check_options(cfg: Any, stage: str, prefix: str = "") -> None:
    """Raise a :class:`UsageError` naming the first option of ``cfg`` (the ``stage``'s options) whose value
    breaks its rule; ``prefix``: how the command line names the stage's options (``"poses."`` for `run`)."""
    for name, rule, must in RULES.get(stage, []):
        if hasattr(cfg, name) and not rule(getattr(cfg, name)):
            raise UsageError(f"--{prefix}{name.replace('_', '-')} {getattr(cfg, name)}: must be {must}")
    if stage == "poses" and cfg.marker_size > cfg.cube_size:
        raise UsageError(f"--{prefix}marker-size {cfg.marker_size}: must be at most the cube's edge "
                         f"(--{prefix}cube-size {cfg.cube_size})")


def check_run_options(cfg: Any) -> None:
    """Every stage's options of a :class:`~plantsplat.pipeline.RunConfig`, named as `plantsplat run` names them."""
    for stage in RULES:
        check_options(getattr(cfg, stage), stage, prefix=f"{stage}.")

"""Checks at the start of `run` and `batch`, before any stage runs: what would otherwise fail (or destroy
something) minutes later.

- the workspace (``--out``) is a folder or can become one;
- every path an option names exists (``--ground-truth``, ``--segment.import-masks``,
  ``--poses.import-transforms``, ``--poses.import-colmap``, ...);
- every option value is one the stages can work with (:mod:`plantsplat.options`);
- the workspace's ``masks/`` were written by plantsplat's own segment stage, never the user's
  (:func:`check_masks_are_ours`: a capture folder's masks are never overwritten).

Example:
    >>> import tempfile
    >>> from plantsplat.pipeline import RunConfig
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     check_run(None, tmp, RunConfig())
"""

from __future__ import annotations

import os
from pathlib import Path

from plantsplat.errors import PlantsplatError, UsageError
from plantsplat.options import check_run_options
from plantsplat.stages import read_record
from plantsplat.workspace import Workspace


def check_workspace_folder(root: str | os.PathLike) -> None:
    """Refuse a workspace path that is a file, or that lies under one (exit code 2)."""
    root = Path(root)
    for p in [root, *root.parents]:
        if p.exists() and not p.is_dir():
            raise UsageError(f"{p}: exists and is not a folder; choose another --out (a new or existing folder)")
        if p.exists():
            return


def option_paths(cfg) -> list[tuple[str, Path | None]]:
    """``(option, path)`` for every path a :class:`~plantsplat.pipeline.RunConfig` names (None when unset)."""
    return [("--ground-truth", cfg.ground_truth), ("--poses.import-colmap", cfg.poses.import_colmap),
            ("--poses.import-transforms", cfg.poses.import_transforms),
            ("--segment.import-masks", cfg.segment.import_masks),
            ("--segment.sam2-checkpoint", cfg.segment.sam2_checkpoint),
            ("--train.lpips-weights", cfg.train.lpips_weights)]


def check_option_paths(cfg) -> None:
    """Refuse a path option that names nothing (exit code 2), before any stage spends time."""
    for option, path in option_paths(cfg):
        if path is not None and not Path(path).exists():
            raise UsageError(f"{path}: not found (given as {option}); check the path")


def check_masks_are_ours(ws: Workspace) -> None:
    """Refuse to replace a ``masks/`` folder that this workspace's segment stage did not write: a capture
    folder's own masks (ground truth, or the user's) are never overwritten, even with --force."""
    if read_record(ws, "segment") is not None or not ws.masks_dir.is_dir():
        return
    if any(p.is_file() for p in ws.masks_dir.iterdir()):
        raise UsageError(f"{ws.masks_dir}: holds masks this workspace's segment stage did not write, and the stage "
                         "would replace them; choose another workspace (--out), or move them to another folder and "
                         "pass it as --segment.import-masks (your masks are left as they are)")


def check_run(source: str | os.PathLike | None, ws_root: str | os.PathLike, cfg) -> None:
    """Every check above for `plantsplat run` (``source``: the video or image folder, or None)."""
    check_workspace_folder(ws_root)
    if source is not None and not Path(source).exists():
        raise PlantsplatError(f"{source}: input not found (a video file or a folder of images)")
    check_option_paths(cfg)
    check_run_options(cfg)
    check_masks_are_ours(Workspace(ws_root))

"""Checkpoints and finished models: where they go, writing them atomically, reading them back.

A run trains in ``WS/.train.partial/`` (:func:`partial_paths`): ``checkpoint.pt`` is written there while
training runs (an interrupted run resumes from it), and the finished folder replaces ``WS/train/`` whole, so
the previous model stays until the new one is complete. ``WS/train/model.pt`` is the finished model, with its
configuration, split and summary.

Example:
    >>> from plantsplat.workspace import Workspace
    >>> model_path(Workspace("ws/plant_01"))
    PosixPath('ws/plant_01/train/model.pt')
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import torch

from plantsplat.errors import PlantsplatError
from plantsplat.io import atomic_path, os_error_message
from plantsplat.train.config import TrainConfig
from plantsplat.workspace import Workspace


def train_paths(ws: Workspace, cfg: TrainConfig) -> dict[str, Path]:
    tdir = Path(cfg.train_dir) if cfg.train_dir else ws.train_dir
    return {
        "dir": tdir,
        "split": tdir / "split.json",
        "ckpt": tdir / "checkpoint.pt",
        "model": tdir / "model.pt",
        "config": tdir / "config.json",
        "metrics": Path(cfg.metrics_path) if cfg.metrics_path else ws.metrics_json,
    }


def partial_paths(paths: dict[str, Path]) -> dict[str, Path]:
    """Where a run writes until it finishes (the keys of :func:`train_paths`): a sibling folder of the train folder,
    ``WS/.train.partial/``, swapped in whole when the model and its metrics are complete (its metrics as
    ``metrics.staged.json``, moved to their own path after the swap)."""
    d = paths["dir"].with_name(f".{paths['dir'].name}.partial")
    return {"dir": d, "split": d / "split.json", "ckpt": d / "checkpoint.pt", "model": d / "model.pt",
            "config": d / "config.json", "metrics": d / STAGED_METRICS}


STAGED_METRICS = "metrics.staged.json"


def model_path(ws: Workspace, train_dir: Path | None = None) -> Path:
    return (Path(train_dir) if train_dir else ws.train_dir) / "model.pt"


def save_checkpoint(path: str | os.PathLike, step: int, params, optimizers, strategy_state: dict, extra: dict) -> None:
    """Atomically save everything needed to resume training at ``step``."""
    blob = {
        "step": step,
        "params": {k: v.detach().clone() for k, v in params.items()},
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "strategy_state": {k: (v.clone() if torch.is_tensor(v) else v) for k, v in strategy_state.items()},
        "extra": extra,
    }
    try:
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)
    except RuntimeError as exc:  # torch's writer reports a full disk as "unexpected pos" or "file write failed"
        raise PlantsplatError(os_error_message(OSError(errno.ENOSPC, str(exc)), path)
                              if "unexpected pos" in str(exc) or "write failed" in str(exc)
                              else f"{path}: could not write the checkpoint ({exc}); re-run to resume") from exc


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`."""
    path = Path(path)
    try:
        blob = torch.load(str(path), map_location="cpu", weights_only=False)
        _ = blob["params"]["means"]
    except Exception as exc:
        raise PlantsplatError(f"{path}: unreadable checkpoint ({type(exc).__name__}); delete it to train from scratch") from exc
    return blob


def params_from_checkpoint(blob: dict) -> torch.nn.ParameterDict:
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v.clone()) for k, v in blob["params"].items()})


def load_model(ws: Workspace, train_dir: Path | None = None) -> tuple[torch.nn.ParameterDict, dict]:
    """The finished model of a workspace: parameters and the checkpoint's ``extra`` (config, split)."""
    p = model_path(ws, train_dir)
    if not p.is_file():
        ck = p.parent.with_name(f".{p.parent.name}.partial") / "checkpoint.pt"
        hint = " (an unfinished run's checkpoint exists: re-run it to finish)" if ck.is_file() else ""
        raise PlantsplatError(f"{p}: no trained model{hint}; run `plantsplat train {ws.root}` first")
    blob = load_checkpoint(p)
    return params_from_checkpoint(blob), blob["extra"]

"""Atomic file output and small readers shared by every stage.

Every file a stage writes goes through these helpers: data is written to a temporary file in the
same folder and renamed into place, so an interrupted run never leaves a half-written output and a
re-run can trust whatever exists.

Example:
    >>> from plantsplat.io import write_json_atomic, read_json
    >>> write_json_atomic("ws/frames.json", {"frames": []})
    >>> read_json("ws/frames.json")["frames"]
    []
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from plantsplat.errors import PlantsplatError

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    ``suffix`` defaults to the target's suffix so that writers which look at the extension
    (OpenCV, PyAV, Open3D) still pick the right format.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        if exc.errno == 28:  # ENOSPC
            raise PlantsplatError(f"{path}: the disk is full; free some space and re-run (finished outputs are kept)") from exc
        raise
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json_atomic(path: str | os.PathLike, data: Any, indent: int = 2) -> None:
    """Write ``data`` as JSON (numpy arrays and scalars allowed) atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent, default=_json_default) + "\n")


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON, turning a missing or corrupt file into a one-line :class:`PlantsplatError`."""
    path = Path(path)
    if not path.is_file():
        raise PlantsplatError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PlantsplatError(f"{path}: not valid JSON ({exc}); delete it and re-run the stage that writes it") from exc


def png_params() -> list[int]:
    """OpenCV ``imwrite`` parameters for fast lossless PNGs: zlib level 1, run-length strategy and the one "sub"
    row filter instead of trying all five per row. A 540x960 RGBA frame: 27 ms against 72 ms with OpenCV's
    defaults, and 10 % smaller (measured here)."""
    import cv2

    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.11
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]
    return params


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8-bit image (H,W), (H,W,3) RGB or (H,W,4) RGBA with OpenCV, atomically (PNGs with
    :func:`png_params`).

    Colour images are given in RGB(A) order; OpenCV's BGR order is handled here.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    params = png_params() if Path(path).suffix.lower() == ".png" else []
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img, params):
            raise PlantsplatError(f"{path}: could not write image")


def read_image(path: str | os.PathLike, mode: str = "rgb") -> np.ndarray:
    """Read an image as uint8 RGB (``mode='rgb'``), RGBA (``'rgba'``) or single channel (``'gray'``)."""
    import cv2

    path = Path(path)
    flag = {"rgb": cv2.IMREAD_COLOR, "rgba": cv2.IMREAD_UNCHANGED, "gray": cv2.IMREAD_GRAYSCALE}[mode]
    img = cv2.imread(str(path), flag)
    if img is None:
        raise PlantsplatError(f"{path}: unreadable or not an image; replace or delete it")
    if mode == "rgb":
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if mode == "rgba":
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGRA)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA)
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img

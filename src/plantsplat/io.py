"""Atomic file output and small readers shared by every stage.

Every file a stage writes goes through these helpers: data is written to a temporary file in the
same folder and renamed into place, so an interrupted run never leaves a half-written output and a
re-run can trust whatever exists.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> from plantsplat.io import write_json_atomic, read_json
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     write_json_atomic(Path(tmp) / "ws" / "frames.json", {"frames": []})
    ...     read_json(Path(tmp) / "ws" / "frames.json")["frames"]
    []
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.log import get_logger

log = get_logger(__name__)

_UMASK = os.umask(0)
os.umask(_UMASK)


def os_error_message(exc: OSError, path: str | os.PathLike | None = None) -> str:
    """One line, in words, for a failed read or write of ``path``: what happened and what to do.

    Example:
        >>> import errno
        >>> os_error_message(OSError(errno.ENOSPC, "No space left on device"), "ws/train/model.pt")
        'ws/train/model.pt: the disk is full; free some space and re-run (finished outputs are kept)'
    """
    where = path if path is not None else (exc.filename or "a file")
    if exc.errno == errno.ENOSPC or exc.errno == errno.EDQUOT:
        return f"{where}: the disk is full; free some space and re-run (finished outputs are kept)"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"{where}: permission denied; make the folder writable or choose another output folder"
    if exc.errno == errno.EROFS:
        return f"{where}: the file system is read-only; choose an output folder on a writable disk"
    if exc.errno == errno.ENOTDIR:
        return f"{where}: a part of this path is a file, not a folder; choose another output folder"
    if exc.errno == errno.EEXIST:
        return f"{where}: already exists and is in the way; move it aside or choose another output folder"
    return f"{where}: {exc.strerror or exc}; check the path, the disk and the permissions"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    ``suffix`` defaults to the target's suffix so that writers which look at the extension
    (OpenCV, PyAV, Open3D) still pick the right format.
    """
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    except OSError as exc:
        raise PlantsplatError(os_error_message(exc, path)) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        raise PlantsplatError(os_error_message(exc, path)) from exc
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def staged_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a fresh folder beside ``path``; when the block succeeds it replaces ``path`` whole.

    A stage writes a folder of outputs (frames, masks, a COLMAP model) into the yielded folder; only a
    finished folder is swapped in (the old one removed after), so an interrupted or failed stage
    leaves the previous outputs as they were and never a mix of old and new files.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.new.", dir=path.parent))
    except OSError as exc:
        raise PlantsplatError(os_error_message(exc, path)) from exc
    os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700; outputs get the usual permissions
    try:
        yield tmp
        replace_dir(tmp, path)
    except OSError as exc:
        remove_tree(tmp)
        raise PlantsplatError(os_error_message(exc, path)) from exc
    except BaseException:
        remove_tree(tmp)
        raise


def replace_dir(new: str | os.PathLike, path: str | os.PathLike) -> None:
    """Put the finished folder ``new`` in the place of ``path`` (the old ``path`` moved aside first, removed after).

    Both must be on the same file system (a sibling, as :func:`staged_dir` and the train stage make).
    """
    new, path = Path(new), Path(path)
    old = None
    if path.exists():
        old = path.with_name(f".{path.name}.old")
        remove_tree(old)
        os.replace(path, old)
    os.replace(new, path)
    if old is not None:
        remove_tree(old)


def remove_tree(path: Path) -> None:
    """Remove a file or a folder with everything in it; nothing when it is not there."""
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink(missing_ok=True)


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


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON, turning a missing or corrupt file into a one-line :class:`PlantsplatError`."""
    path = Path(path)
    if not path.is_file():
        raise PlantsplatError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PlantsplatError(f"{path}: not valid JSON ({exc}); delete it and re-run the stage that writes it") from exc


def csv_cell(value: Any) -> Any:
    """A CSV cell a spreadsheet shows as text: a string starting with ``= + - @`` (or a tab or carriage return) is
    a formula to Excel and LibreOffice, so it gets a leading ``'``; numbers and other text stay as they are.

    Example:
        >>> csv_cell("=1+1"), csv_cell("plant01"), csv_cell(-2.5)
        ("'=1+1", 'plant01', -2.5)
    """
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value


def png_params() -> list[int]:
    """OpenCV ``imwrite`` parameters for fast lossless PNGs: zlib level 1, run-length strategy and the one "sub"
    row filter instead of trying all five per row. A 540x960 RGBA frame: 27 ms against 72 ms with OpenCV's
    defaults, and 10 % smaller (measured here)."""
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module

    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV >= 4.11
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]
    return params


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8-bit image (H,W), (H,W,3) RGB or (H,W,4) RGBA with OpenCV, atomically (PNGs with
    :func:`png_params`).

    Colour images are given in RGB(A) order; OpenCV's BGR order is handled here.
    """
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    params = png_params() if Path(path).suffix.lower() == ".png" else []
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img, params):
            raise PlantsplatError(f"{path}: could not write image")


_STDERR_REDIRECT = threading.RLock()
"""Held while the process's stderr is sent elsewhere: the file descriptor is the process's, not a thread's, and two
threads redirecting it at once restore each other's sink instead of the real stderr (one thread may nest them)."""
TAIL_BYTES = 4096
"""Bytes at an image file's end searched for its end marker (some cameras pad a JPEG after it)."""
END_MARKERS = {b"\xff\xd8": b"\xff\xd9", b"\x89PNG\r\n\x1a\n": b"IEND"}
"""Each format's first bytes and the marker its last bytes hold: JPEG's end-of-image, PNG's IEND chunk."""


def cut_short(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a JPEG or PNG whose data stops before its end marker (a copy or download cut short)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            end = next((e for start, e in END_MARKERS.items() if head.startswith(start)), None)
            if end is None:
                return False
            size = f.seek(0, os.SEEK_END)
            f.seek(max(len(head), size - TAIL_BYTES))
            return end not in f.read()
    except OSError:
        return False  # the decoder says the file is unreadable


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Send what C libraries print on the process's stderr during the block nowhere (Python's own writes to it
    too). The descriptor is the process's: whatever another thread prints meanwhile is lost as well, so this is kept
    to short blocks (a damaged file's decoding, COLMAP's calls)."""
    with _STDERR_REDIRECT, open(os.devnull, "wb") as sink:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)


def imread_quietly(path: str | os.PathLike, flag: int) -> np.ndarray | None:
    """``cv2.imread`` where a JPEG or PNG cut short gives one warning naming the file (or, undecodable, None for the
    caller's error) instead of the decoder's raw "Premature end of JPEG file" or "libpng error: Read Error". The file
    is checked before decoding, so that the process's stderr is left alone for every whole file (other threads log
    and draw progress bars on it)."""
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module

    if not cut_short(path):
        return cv2.imread(str(path), flag)
    with native_stderr_silenced():
        img = cv2.imread(str(path), flag)
    if img is not None:
        log.warning("%s: damaged image (the file is cut short); it is used as far as it could be decoded", path)
    return img


def read_image(path: str | os.PathLike, mode: str = "rgb") -> np.ndarray:
    """Read an image as uint8 RGB (``mode='rgb'``), RGBA (``'rgba'``) or single channel (``'gray'``)."""
    import cv2  # deferred: OpenCV is slow to load, and the CLI imports this module

    path = Path(path)
    flag = {"rgb": cv2.IMREAD_COLOR, "rgba": cv2.IMREAD_UNCHANGED, "gray": cv2.IMREAD_GRAYSCALE}[mode]
    img = imread_quietly(path, flag)
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

"""One process at a time per workspace: ``WS/.plantsplat/lock`` names the process that works on it.

A second ``plantsplat`` command on the same workspace (a second ``run``, a stage command, a batch
plant) is refused with one line naming the other process, instead of both redoing the same stages
over each other's files. A lock whose process is gone (killed, crashed, the machine restarted) is
taken over with a warning. The lock is re-entrant within a process: ``run`` holds it for the whole
pipeline and each stage inside takes it again freely.

Example:
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     with workspace_lock(tmp):
    ...         holder(tmp)["pid"] == os.getpid()
    True
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from plantsplat.errors import PlantsplatError
from plantsplat.io import os_error_message
from plantsplat.log import get_logger

log = get_logger(__name__)

LOCK_FILE = ".plantsplat/lock"
_held: dict[Path, int] = {}  # lock path -> depth, in this process


def lock_path(root: str | os.PathLike) -> Path:
    return Path(root) / LOCK_FILE


def holder(root: str | os.PathLike) -> dict | None:
    """``{"pid", "host", "since"}`` of the process holding the workspace's lock, or None (no lock, or unreadable)."""
    try:
        data = json.loads(lock_path(root).read_text())
        return data if isinstance(data, dict) and isinstance(data.get("pid"), int) else None
    except (OSError, ValueError):
        return None


def alive(info: dict) -> bool:
    """Whether the lock's process still runs (a process on another machine is taken to be running)."""
    if info.get("host") != socket.gethostname():
        return True
    try:
        os.kill(info["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process with that id
        return True
    return True


def _try_create(path: Path) -> bool:
    """Create the lock file whole (written aside, then hard-linked in: never seen half-written); False when one
    exists already."""
    fd, tmp = tempfile.mkstemp(prefix=".lock.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump({"pid": os.getpid(), "host": socket.gethostname(),
                       "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}, f)
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    finally:
        os.unlink(tmp)


def _acquire(root: Path, path: Path) -> None:
    for _ in range(10):
        if _try_create(path):
            return
        info = holder(root)
        if info is None:  # vanished meanwhile, or unreadable: a crash while it was made
            age = time.time() - path.stat().st_mtime if path.exists() else 0.0
            if age < 5.0:
                time.sleep(0.1)
                continue
        elif info["pid"] != os.getpid() and alive(info):
            raise PlantsplatError(
                f"{root}: in use by process {info['pid']} on {info.get('host')} (since {info.get('since')}); wait "
                f"for it to finish or stop it (kill {info['pid']}), then run again")
        log.warning("%s: taking over the lock of process %s, which is no longer running", root,
                    None if info is None else info["pid"])
        path.unlink(missing_ok=True)
    raise PlantsplatError(f"{path}: could not take the workspace's lock; delete the file if no plantsplat runs on it")


@contextlib.contextmanager
def workspace_lock(root: str | os.PathLike) -> Iterator[None]:
    """Hold the workspace's lock for the block (see the module docstring); raises :class:`PlantsplatError`
    naming the other process when another live process holds it."""
    root = Path(root)
    path = lock_path(root)
    key = path.resolve()
    if _held.get(key):
        _held[key] += 1
    else:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            _acquire(root, path)
        except OSError as exc:
            raise PlantsplatError(os_error_message(exc, path)) from exc
        _held[key] = 1
    try:
        yield
    finally:
        _held[key] -= 1
        if not _held[key]:
            del _held[key]
            info = holder(root)
            if info is not None and info["pid"] == os.getpid():
                path.unlink(missing_ok=True)

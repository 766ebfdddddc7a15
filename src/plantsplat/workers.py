"""Worker processes: started with :func:`spawn_worker`, each ends with the stage that started it.

A worker is a separate interpreter (``python -m module args``) rather than :mod:`multiprocessing`, so that no user's
main module is imported again in it. In the worker, :func:`worker_start` leaves Ctrl-C to the stage (which stops its
workers), ends the worker when the stage dies, and can lower its priority.

Usage:
    proc = spawn_worker("plantsplat.poses.map_worker", [str(db), ...], here)  # in the stage
    worker_start(lowest_priority=True)  # first thing in the worker's main()
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import plantsplat

PARENT_ENV = "PLANTSPLAT_WORKER_PARENT"
"""Environment variable giving a worker process the process id of the stage that started it."""
WORKER_LOG = "log.txt"
"""A worker process's output, in its folder."""
PR_SET_PDEATHSIG = 1
"""Linux's prctl option: the signal this process gets when the thread that started it ends."""
LOWEST_PRIORITY = 19
"""The niceness a background worker takes (the lowest priority on Linux and macOS)."""


def spawn_worker(module: str, args: list[str], here: Path | None) -> subprocess.Popen:
    """``python -m module args`` running this process's plantsplat (its folder first on the worker's path), in the
    folder ``here`` (nothing of the caller's folder on its path), its output in ``here/log.txt`` (``here`` None: in
    the temporary folder, its output dropped); it ends with this process (:data:`PARENT_ENV`)."""
    env = {**os.environ, PARENT_ENV: str(os.getpid()), "PYTHONPATH": os.pathsep.join(
        x for x in (str(Path(plantsplat.__file__).resolve().parents[1]), os.environ.get("PYTHONPATH")) if x)}
    cmd = [sys.executable, "-m", module, *args]
    if here is None:
        return subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, cwd=tempfile.gettempdir())
    with open(here / WORKER_LOG, "wb") as log_file:
        return subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT,
                                cwd=here)


def stop_worker(proc: subprocess.Popen | None) -> None:
    """End a worker that still runs (Ctrl-C or an error in the stage: it does not go on); None or an ended one is
    left as it is."""
    if proc is not None and proc.poll() is None:
        proc.kill()
        proc.wait()


def worker_said(here: Path) -> str:
    """The last line a worker process wrote in its folder ``here``, and where the rest is."""
    lines = (here / WORKER_LOG).read_text(errors="replace").strip().splitlines() or ["no message"]
    return f"{lines[-1]}; see {here / WORKER_LOG}"


def die_with_parent() -> None:
    """End this process when the stage that started it dies, however it dies: a SIGKILL or the out-of-memory killer
    gives the stage no chance to stop its workers, which would go on matching, orphaned, for minutes (Linux: the
    kernel sends SIGKILL; elsewhere nothing changes). A stage already gone (``PARENT_ENV`` no longer our parent)
    ends it at once."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    parent = int(os.environ.get(PARENT_ENV, "0"))
    if parent and os.getppid() != parent:
        sys.exit(1)


def worker_start(lowest_priority: bool = False) -> None:
    """What a worker does first: Ctrl-C is left to the stage, which stops it; it ends with the stage
    (:func:`die_with_parent`); with ``lowest_priority`` it takes niceness :data:`LOWEST_PRIORITY`, so that it runs on
    the cycles the stage leaves idle (where the platform has ``os.nice``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent()
    if lowest_priority and hasattr(os, "nice"):  # not on Windows
        os.nice(LOWEST_PRIORITY)

"""Worker processes: started with :func:`spawn_worker` or :func:`start_forked`, each ends with the stage that
started it.

A worker is a separate interpreter (``python -m module args``) rather than :mod:`multiprocessing`, so that no user's
main module is imported again in it. In the worker, :func:`worker_start` leaves Ctrl-C to the stage (which stops its
workers), ends the worker when the stage dies, and can lower its priority.

:func:`start_forked` is for a computation that must give exactly what it gives in the stage's own process, run beside
the stage's next step: a child forked from the stage holds the same objects at the same addresses (a COLMAP model
written out and read back is adjusted in another order, and comes out different in the last bits). Linux only; where
there is no fork, or the child fails, the computation runs in the stage's process when its result is asked for.

Usage:
    proc = spawn_worker("plantsplat.poses.map_worker", [str(db), ...], here)  # in the stage
    worker_start(lowest_priority=True)  # first thing in the worker's main()
    beside = start_forked(lambda: adjust(copy))  # then the stage's own step, then beside.result()
"""

from __future__ import annotations

import ctypes
import os
import pickle
import select
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Generic, TypeVar

import plantsplat
from plantsplat.log import get_logger

log = get_logger(__name__)
T = TypeVar("T")

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


def _die_with_this_process() -> None:
    """Linux: SIGKILL to this process when the thread that started it ends."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def die_with_parent() -> None:
    """End this process when the stage that started it dies, however it dies: a SIGKILL or the out-of-memory killer
    gives the stage no chance to stop its workers, which would go on matching, orphaned, for minutes (Linux: the
    kernel sends SIGKILL; elsewhere nothing changes). A stage already gone (``PARENT_ENV`` no longer our parent)
    ends it at once."""
    _die_with_this_process()
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


class Forked(Generic[T]):
    """``fn()`` started by :func:`start_forked`; :meth:`result` waits for its value, :meth:`stop` ends it unasked."""

    def __init__(self, fn: Callable[[], T], pid: int | None, fd: int | None):
        self._fn, self._pid, self._fd = fn, pid, fd

    def result(self, timeout: float | None = None) -> T:
        """``fn()``'s value from the child; computed here instead when there is no child, it failed, or it gave
        nothing within ``timeout`` seconds (then it is ended: a child stuck on a lock another thread held at the
        fork must not stop the stage)."""
        if self._pid is None:
            return self._fn()
        data = self._read(timeout)
        if data is not None:
            _, status = os.waitpid(self._pid, 0)
            self._pid = None
            if os.waitstatus_to_exitcode(status) == 0 and data:
                return pickle.loads(data)
        self.stop()
        log.debug("the forked computation failed or timed out (%s s); computing it here", timeout)
        return self._fn()

    def _read(self, timeout: float | None) -> bytes | None:
        """Everything the child writes until it closes the pipe; None when ``timeout`` passes first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        chunks = []
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self._fd], [], [], wait)[0]:
                return None
            chunk = os.read(self._fd, 1 << 20)
            if not chunk:
                os.close(self._fd)
                self._fd = None
                return b"".join(chunks)
            chunks.append(chunk)

    def stop(self) -> None:
        """End the child if it still runs (an error or Ctrl-C in the stage); nothing after :meth:`result`."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._pid is not None:
            try:
                os.kill(self._pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            os.waitpid(self._pid, 0)
            self._pid = None


def start_forked(fn: Callable[[], T]) -> Forked[T]:
    """Start ``fn()`` in a child forked now (Linux), beside what this process does next; its value comes back
    pickled. The child sees this process's objects as they are now and changes only its own copies: ``fn`` must not
    depend on what the caller changes meanwhile, and its effects reach the caller only through its value. The child
    ignores Ctrl-C (the stage stops it) and dies with this process. Call :meth:`Forked.stop` in a ``finally``."""
    if not sys.platform.startswith("linux"):  # fork is unsafe on macOS and absent on Windows
        return Forked(fn, None, None)
    parent = os.getpid()
    try:
        r, w = os.pipe()
    except OSError as exc:  # no descriptors left: compute it here
        log.debug("no pipe for a forked computation (%s); computing it here", exc)
        return Forked(fn, None, None)
    try:
        with warnings.catch_warnings():  # Python 3.12+ warns of any fork beside native threads: see result()'s timeout
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except OSError as exc:  # a process limit (EAGAIN) or no memory to spare (ENOMEM): compute it here
        os.close(r)
        os.close(w)
        log.debug("could not fork (%s); computing it here", exc)
        return Forked(fn, None, None)
    if pid == 0:  # pragma: no cover - the child (coverage does not follow it)
        code = 1
        try:
            os.close(r)
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            _die_with_this_process()
            if os.getppid() != parent:  # the stage ended before the line above
                os._exit(1)
            data = pickle.dumps(fn(), protocol=pickle.HIGHEST_PROTOCOL)
            with os.fdopen(w, "wb") as f:
                f.write(data)
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    return Forked(fn, pid, r)

"""Per-stage time and peak memory measurement (Linux: VmHWM reset through /proc/self/clear_refs).

Example:
    >>> with StageMeter() as m:
    ...     _ = bytearray(10_000_000)
    >>> m.seconds >= 0 and m.peak_rss_mb > 0
    True
"""

from __future__ import annotations

import importlib
import os
import platform
import resource
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import plantsplat
from plantsplat.log import progress

T = TypeVar("T")
R = TypeVar("R")


def _read_status(key: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1]) / 1024.0  # kB -> MB
    except OSError:
        return None
    return None


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _cpu_seconds() -> float:
    """CPU seconds (user and system) of this process and of its children that ended."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class StageMeter:
    """Measures wall time, CPU time (this process's threads and the processes it waited for, such as the video
    encoder) and the peak resident memory of this process during a ``with`` block.

    Where the kernel lets a process reset its high-water mark, the peak is exact; otherwise a
    background thread samples the resident size every 50 ms.
    """

    def __init__(self):
        self.seconds = 0.0
        self.cpu_seconds = 0.0
        self.peak_rss_mb = 0.0
        self._sampler: threading.Thread | None = None
        self._stop = threading.Event()
        self._sampled = 0.0

    def _sample(self):
        while not self._stop.wait(0.05):
            rss = _read_status("VmRSS") or 0.0
            self._sampled = max(self._sampled, rss)

    def __enter__(self):
        self._exact = _reset_peak()
        if not self._exact:
            self._sampled = _read_status("VmRSS") or 0.0
            self._sampler = threading.Thread(target=self._sample, daemon=True)
            self._sampler.start()
        self._t0, self._cpu0 = time.perf_counter(), _cpu_seconds()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self._t0
        self.cpu_seconds = _cpu_seconds() - self._cpu0
        if self._exact:
            self.peak_rss_mb = _read_status("VmHWM") or 0.0
        else:
            self._stop.set()
            if self._sampler is not None:
                self._sampler.join()
            self.peak_rss_mb = max(self._sampled, _read_status("VmRSS") or 0.0)
            if self.peak_rss_mb == 0.0:  # no /proc: fall back to the process-lifetime peak
                self.peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        return False


def usable_cores() -> int:
    """Cores this process may use for its own thread pools: the share ``plantsplat batch`` gives each of its workers
    (``NUMBA_NUM_THREADS``, which it sets), else the cores the process may run on (its CPU affinity)."""
    share = os.environ.get("NUMBA_NUM_THREADS", "")
    if share.isdigit() and int(share) > 0:
        return int(share)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity on this platform (macOS)
        return os.cpu_count() or 1


def map_on_cores(fn: Callable[[T], R], items: Iterable[T], description: str) -> Iterator[R]:
    """``fn`` of each of ``items`` on :func:`usable_cores` threads (for work that releases the GIL: decoding, OpenCV),
    yielded in the items' order under a progress bar; an error or Ctrl-C stops the items not yet started, and the pool
    ends before the error goes on."""
    items = list(items)
    with ThreadPoolExecutor(max_workers=usable_cores()) as pool:
        results = pool.map(fn, items)
        try:
            yield from progress(results, description, total=len(items))
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise


def machine_info() -> dict:
    """CPU, cores, memory, load and library versions, for benchmark results and run.json."""
    info: dict = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
        mem = Path("/proc/meminfo").read_text().splitlines()[0].split()[1]
        info["mem_total_gb"] = round(int(mem) / 1024 / 1024, 1)
    except OSError:
        pass
    versions = {}
    for mod in ["plantsplat", "numpy", "torch", "numba", "cv2", "pycolmap", "open3d"]:
        try:
            versions[mod] = getattr(importlib.import_module(mod), "__version__", "?")
        except Exception:
            versions[mod] = None
    info["versions"] = versions
    info["omp"] = plantsplat.omp_setting()
    try:
        import torch  # deferred: torch is slow to load, and the CLI imports this module

        info["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    except Exception:
        info["cuda"] = None
    return info

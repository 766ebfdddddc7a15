"""Whether numba's cache holds this version's CPU kernels, told without loading numba or torch.

The kernel warm-up (:mod:`plantsplat.train.warmup`) leaves a stamp when it has compiled or loaded every kernel: a
file named by a digest of the kernel modules' sources, numba's version and Python's, next to numba's cache of them
(``NUMBA_CACHE_DIR``, else the ``raster/__pycache__`` folder numba writes into). Deleting the cache deletes the stamp;
a change to a kernel, numba or Python names another stamp. ``plantsplat run`` starts the warm-up only where the stamp
is missing, and then at normal priority: on a cold cache the compiling is worth the cycles it takes from the first
stages, and on a warm one nothing is started.

Usage:
    if not kernels_cached():
        ...  # start the warm-up; it calls mark_kernels_cached() at its end
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from importlib import metadata
from pathlib import Path

import plantsplat

KERNEL_MODULES = ("cpu.py", "cpu_order.py", "cpu_projection.py", "sh_cpu.py", "ssim.py", "numba_config.py")
"""The files of ``plantsplat/raster/`` whose kernels numba caches (``numba_config``: the flags they share)."""


def kernel_sources_digest(raster: Path) -> str:
    """A digest of what numba's cache of the kernels in the folder ``raster`` is valid for: numba's and Python's
    versions, this machine's processor, and each kernel module's source with its size and modification time
    (numba drops its cached kernels of a file whose time or size changed: a reinstall, a checkout there and back)."""
    h = hashlib.sha256(f"{metadata.version('numba')} {sys.version_info[:3]} {processor_model()}".encode())
    for name in KERNEL_MODULES:
        path = raster / name
        st = path.stat()
        h.update(f"{name} {st.st_size} {st.st_mtime_ns}\n".encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def processor_model() -> str:
    """The processor's model (numba's cached kernels are compiled for it), without loading numba."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()}"


def _stamp() -> Path:
    """Where this version's stamp is (it may not exist)."""
    raster = Path(plantsplat.__file__).resolve().parent / "raster"
    folder = Path(os.environ["NUMBA_CACHE_DIR"]) if os.environ.get("NUMBA_CACHE_DIR") else raster / "__pycache__"
    return folder / f"plantsplat-kernels-{kernel_sources_digest(raster)}.stamp"


def kernels_cached() -> bool:
    """Whether the warm-up has cached this version's kernels (see the module's docstring). Where the kernels' sources
    cannot be read, numba cannot cache them either, and there is nothing to warm up: True."""
    try:
        return _stamp().is_file()
    except OSError:
        return True


def mark_kernels_cached() -> None:
    """Leave the stamp; where numba's cache folder cannot be written (numba then caches elsewhere) none is left, and
    the next run warms up again."""
    try:
        stamp = _stamp()
        stamp.parent.mkdir(parents=True, exist_ok=True)
        stamp.touch()
    except OSError:
        pass

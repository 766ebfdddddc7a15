"""plantsplat: object-centric 3D Gaussian Splatting of potted plants, with metric traits."""

import os as _os
import sys as _sys

# OpenMP waiting, set before anything imports torch or numba. Each libgomp (PyTorch's bundled one, and the system's
# that numba's "omp" threading layer loads) reads it once, when it is loaded (at `import torch` / the first numba
# parallel kernel), so it has to be in the environment before those imports: every entry point (the `plantsplat`
# CLI, `python -m plantsplat`, `import plantsplat.train`) imports this package first.
#
# A training step runs dozens of short parallel kernels with single-threaded torch work between them. Idle
# OpenMP threads that spin a little before they sleep pick the next kernel up at once; threads that sleep at
# once (OMP_WAIT_POLICY=PASSIVE) must be woken for each. Threads that spin long (libgomp's default) starve
# everything else when the cores are already busy. Measured (object mode, 800 steps of the training
# benchmark's seed 0, 2 cores): idle machine PASSIVE 28-43 s, GOMP_SPINCOUNT=20000 22-28 s, 3000 32 s, libgomp's
# default long spin in PyTorch's pool (numba's asleep at once) 27 s; with two busy processes beside it PASSIVE 45 s,
# 20000 78 s, 3000 60 s, that default 154 s. So:
# a short spin when the machine is not busy at import, PASSIVE when its load already fills the cores. A
# user's own OMP_WAIT_POLICY or GOMP_SPINCOUNT wins.
_OMP_SPIN = "20000"
_OMP_KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
_OMP_CHOICE_VAR = "PLANTSPLAT_OMP_CHOICE"  # what a plantsplat process chose, so its workers can tell it from a user's


def _omp_env() -> str:
    return ", ".join(f"{k}={_os.environ[k]}" for k in _OMP_KEYS if k in _os.environ)


_OMP_PRESET = any(k in _os.environ for k in _OMP_KEYS)
_OMP_INHERITED = _OMP_PRESET and _os.environ.get(_OMP_CHOICE_VAR) == _omp_env()
# importing numba alone is harmless (its OpenMP pool loads with the first parallel kernel)
_OMP_TOO_LATE = not _OMP_PRESET and ("torch" in _sys.modules or "numba.np.ufunc.omppool" in _sys.modules)


def _busy() -> bool:
    try:
        return _os.getloadavg()[0] >= (_os.cpu_count() or 1)
    except (AttributeError, OSError):  # no load average (Windows)
        return False


if not _OMP_PRESET:
    if _busy():
        _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    else:
        _os.environ["GOMP_SPINCOUNT"] = _OMP_SPIN
    _os.environ[_OMP_CHOICE_VAR] = _omp_env()


def omp_setting() -> str:
    """How OpenMP threads wait in this process (for logs and result files)."""
    if _OMP_TOO_LATE:
        return "libgomp default (torch/numba imported before plantsplat)"
    if _OMP_INHERITED:
        return _omp_env() + " (chosen by the parent plantsplat process)"
    return _omp_env() + (" (set by the user)" if _OMP_PRESET else " (chosen at import)")


def omp_wait_policy_note() -> str | None:
    """Why OpenMP may not wait as plantsplat chose in this process, or ``None`` when it does.

    torch or numba imported before plantsplat (without ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` in the
    environment) have already initialised OpenMP with libgomp's default, long spinning; training can then run
    several times slower when other processes keep the cores busy.
    """
    if _OMP_TOO_LATE:
        return ("torch/numba were imported before plantsplat, so OpenMP threads spin long between parallel "
                "regions (slow when the cores are busy); set GOMP_SPINCOUNT=20000 (or OMP_WAIT_POLICY=PASSIVE) in "
                "the environment, or import plantsplat first")
    return None


__version__ = "0.1.0"

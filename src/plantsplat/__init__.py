"""plantsplat: object-centric 3D Gaussian Splatting of potted plants, with metric traits."""

import os as _os
import sys as _sys

# OpenMP wait policy, set before anything imports torch or numba. PyTorch (its bundled libgomp) and
# numba's "omp" threading layer (the system libgomp) each keep their own OpenMP thread pool, and by
# default (ACTIVE) idle OpenMP threads spin for a while after every parallel region. On a 2-core
# machine the two pools then steal the cores from each other: a 448 px training iteration took 0.9 s
# instead of 0.057 s, and a 600-step object-mode run on a 270x480 capture 0.111 s/step (86 CPU-s)
# instead of 0.061 s/step (37 CPU-s) with PASSIVE. libgomp reads the variable once, when the library
# is loaded (i.e. at `import torch` / the first numba parallel kernel), so it has to be in the
# environment before those imports: every entry point (the `plantsplat` CLI, `python -m plantsplat`,
# `import plantsplat.train`) imports this package first. setdefault: a user's own setting wins.
_OMP_PRESET = "OMP_WAIT_POLICY" in _os.environ
# importing numba alone is harmless (its OpenMP pool loads with the first parallel kernel)
_OMP_TOO_LATE = not _OMP_PRESET and ("torch" in _sys.modules or "numba.np.ufunc.omppool" in _sys.modules)
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def omp_wait_policy_note() -> str | None:
    """Why the OpenMP wait policy may not be PASSIVE in this process, or ``None`` when it is set.

    torch or numba imported before plantsplat (without ``OMP_WAIT_POLICY`` in the environment) have
    already initialised OpenMP with the default spinning policy; training can then run ~2x slower on
    few cores.
    """
    if _OMP_TOO_LATE:
        return ("torch/numba were imported before plantsplat, so OpenMP threads spin between parallel "
                "regions (slow on few cores); set OMP_WAIT_POLICY=PASSIVE in the environment, or import "
                "plantsplat first")
    return None


__version__ = "0.1.0"

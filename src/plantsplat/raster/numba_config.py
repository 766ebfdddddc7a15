"""numba settings every CPU kernel shares, chosen once, before any kernel is compiled.

- The threading layer: OpenMP first (the TBB that some wheels bring is too old for numba and would only print a
  warning).
- ``FASTMATH``: the fast-math flags of the compositing and SSIM kernels. Not ``contract`` (fusing a multiply and
  an add into one FMA): a kernel numba compiles in the running process and the same kernel loaded from its cache
  were measured to fuse differently, so the first run after an install or an upgrade gave other images and
  gradients (1e-7 apart, then a different quick model and different masks) than every later run. The
  projection kernels, where the remaining flags changed results between the two as well, and the SH kernels are
  compiled without fast math (they cost little: a training step is 2-4 % slower). ``tests/test_raster.py``
  checks that a freshly compiled kernel and a cached one agree bit for bit.

Each kernel module imports this module. numba notices a change to a kernel's own file only: after changing these
settings, touch the kernel modules (or clear their caches).
"""

import numba

numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

FASTMATH = frozenset({"reassoc", "arcp", "nsz", "afn"})
"""Reassociation (vectorised sums), reciprocals, no signed zeros, approximate functions; never ``contract``."""

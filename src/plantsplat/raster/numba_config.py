"""numba's threading layer for the CPU kernels, chosen once, before any kernel is compiled.

OpenMP first: the TBB that some wheels bring is too old for numba and would only print a warning.
Each kernel module imports this module.
"""

import numba

numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

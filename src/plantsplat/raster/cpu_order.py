"""The CPU compositor's depth order (:mod:`plantsplat.raster.cpu`): the visible Gaussians front to back.

:func:`depth_order` is a stable least-significant-digit radix sort of the depths' float32 bit patterns (non-negative
float32 values order like their bits): three passes of 11, 11 and 10 bits, a pass skipped where every key has the
same digit. Stable, so equal depths keep the index order: the order a sort of the 64-bit keys (depth bits, index)
gives, at about five times its speed (0.24 ms against 1.34 ms for 40,000 Gaussians on the 2-core AMD EPYC,
2026-11-30). It runs on one thread, between the compositor's parallel kernels, once per render.

Example:
    >>> import numpy as np
    >>> depth_order(np.array([2.0, 1.0, 2.0, 0.5], np.float32), np.array([1, 1, 1, 0])).tolist()
    [1, 0, 2]
"""

from __future__ import annotations

import numpy as np
from numba import njit

import plantsplat.raster.numba_config  # noqa: F401  (numba settings every kernel shares)


@njit(cache=True)
def _visible_keys(depths, counts):  # pragma: no cover - numba
    """The indices with ``counts > 0`` (increasing) and their depths' bit patterns, a depth below zero (or NaN, or
    -0.0) taken as 0."""
    m = 0
    for i in range(counts.shape[0]):
        if counts[i] > 0:
            m += 1
    idx = np.empty(m, np.int64)
    z = np.empty(m, np.float32)
    k = 0
    for i in range(counts.shape[0]):
        if counts[i] > 0:
            idx[k] = i
            d = depths[i]
            z[k] = d if d > 0 else np.float32(0.0)
            k += 1
    return z.view(np.uint32), idx


@njit(cache=True)
def _radix(keys, idx):  # pragma: no cover - numba
    """``idx`` stably sorted by ``keys`` (uint32)."""
    n = keys.shape[0]
    hist = np.zeros((3, 2048), np.int64)
    for i in range(n):
        k = keys[i]
        hist[0, k & 2047] += 1
        hist[1, (k >> 11) & 2047] += 1
        hist[2, k >> 22] += 1
    a_k, a_i = keys.copy(), idx.copy()
    b_k, b_i = np.empty_like(keys), np.empty_like(idx)
    shift = 0
    for p in range(3):
        h = hist[p]
        nonzero = 0
        for d in range(2048):
            if h[d] > 0:
                nonzero += 1
        if nonzero > 1:  # a pass where every key has the same digit moves nothing
            acc = 0
            for d in range(2048):
                c = h[d]
                h[d] = acc
                acc += c
            for i in range(n):
                k = a_k[i]
                d = (k >> shift) & 2047
                j = h[d]
                h[d] = j + 1
                b_k[j] = k
                b_i[j] = a_i[i]
            a_k, b_k = b_k, a_k
            a_i, b_i = b_i, a_i
        shift += 11
    return a_i


def depth_order(depths: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Indices of the Gaussians with ``counts > 0``, front to back (float32 ``depths``, a depth below zero taken as
    0), equal depths in index order: int64 [m]."""
    keys, idx = _visible_keys(np.ascontiguousarray(depths, np.float32), counts)
    return _radix(keys, idx)

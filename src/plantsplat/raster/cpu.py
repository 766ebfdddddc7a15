"""CPU backend: tile-parallel numba kernels for compositing, with a hand-written backward pass.

Projection and SH colours are vectorised PyTorch (:mod:`plantsplat.raster.projection`, autograd
differentiates them); this module composites the projected 2D Gaussians, which is where almost all
the time goes. The steps, all in float32:

1. ``_bin``: tile boxes from the screen radii (as gsplat, parallel over Gaussians), visible
   Gaussians sorted once by a 64-bit (depth, index) key with numpy's integer sort, then a counting
   sort into per-tile lists, so each tile's list is front to back.
2. ``_forward_render`` / ``_forward_train``: parallel over workers, each taking every
   ``n_workers``-th non-empty tile from a list sorted by work (empty tiles are skipped entirely);
   within a tile, one Gaussian at a time in depth order, vectorised over 8-pixel column blocks: the
   tile's pixels are stored block by block (``p = (block * ts + row) * 8 + lane``), so the rows
   and column blocks a Gaussian's screen radius reaches are contiguous runs of whole vectors. A
   tile stops once every pixel's transmittance has reached the stop threshold. The train variant
   also saves per pixel the final transmittance and the list position where the pixel stopped.
3. ``_backward``: the same tiles back to front, recovering each Gaussian's transmittance by division;
   gradients are written per (tile, Gaussian) intersection (no atomics, no races, deterministic)
   and summed per Gaussian afterwards (``_reduce``).

Under ``torch.no_grad()`` (or when no input needs a gradient) only ``_bin`` and ``_forward_render`` run
and nothing is kept.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

# OpenMP first: the TBB that some wheels bring is too old for numba and would only print a warning
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
from torch import Tensor

_F32 = np.float32
_ZERO = _F32(0.0)
_HALF = _F32(0.5)
_ONE = _F32(1.0)
_ALPHA_MAX = _F32(0.999)
_ALPHA_MIN = _F32(1.0 / 255.0)
_T_EPS = _F32(1e-4)
# fast-math without the no-NaN/no-Inf assumptions (inputs are validated, but be safe)
_FM = {"reassoc", "contract", "arcp", "nsz", "afn"}
_NGRAD = 10  # per-intersection gradient: mean x, mean y, conic a, b, c, opacity, r, g, b, depth
_LANES = 8  # pixel loops run over 8-column blocks (one AVX2 float32 vector); tile_size is a multiple
_SIG_MAX = _F32(6.0)  # exp(-6) < 1/255: larger sigma can never give a visible alpha
# exp(-x) ~ sum_k _EXP_C[k] x^k on [0, 0.75] (see _exp_neg)
_EXP_C = (_ONE, _F32(-0.9999997019767761), _F32(0.4999932646751404), _F32(-0.1666114628314972),
          _F32(0.04145379737019539), _F32(-0.007908405736088753), _F32(0.0009540405590087175))
_TWO = _F32(2.0)
_NEVER = _F32(2.0**30)  # larger than any tile-list position (float32-exact)


@njit(inline="always", fastmath=_FM, cache=True)
def _exp_neg(s):  # pragma: no cover - numba
    """exp(-s) for s clamped to [0, 6], in float32 arithmetic the compiler can vectorise.

    libm's expf is a scalar call that stops the pixel loop from vectorising, so this is
    exp(-s) = exp(-s/8)^8 with a degree-6 polynomial for exp(-x) on [0, 0.75] (least squares in
    relative error on Chebyshev nodes, exact at 0) and three squarings: 10 vector operations and no
    selects. Max relative error 1.5e-6 on [0, 6] (mostly float32 rounding doubled by each squaring),
    far below what the 8-bit images or the gradients can resolve.
    """
    x = min(max(s, _ZERO), _SIG_MAX) * _F32(0.125)
    p = _EXP_C[6]
    p = p * x + _EXP_C[5]
    p = p * x + _EXP_C[4]
    p = p * x + _EXP_C[3]
    p = p * x + _EXP_C[2]
    p = p * x + _EXP_C[1]
    p = p * x + _ONE
    p = p * p
    p = p * p
    return p * p


@njit(inline="always", cache=True)
def _span(m, r, origin, ts):  # pragma: no cover - numba
    """Tile-local pixel range [lo, hi) whose centres lie within r + 0.05 of m along one axis.

    Beyond the screen radius r (>= extent * sqrt(cov_ii), with extent = sqrt(2 ln(255 opacity)))
    the Mahalanobis distance alone makes alpha < 1/255, so those pixels can be skipped exactly.
    """
    lo = min(max(math.ceil(m - _F32(r) - _F32(0.55)) - origin, 0.0), ts)
    hi = min(max(math.floor(m + _F32(r) - _F32(0.45)) - origin + 1.0, 0.0), ts)
    return int(lo), int(hi)


@njit(parallel=True, cache=True)
def _boxes(means2d, radii, tile_size, tiles_x, tiles_y, box, counts):  # pragma: no cover - numba
    """Tile box [x0, y0, x1, y1) of every Gaussian from its screen radii (as gsplat) and its tile count."""
    ts = _F32(tile_size)
    for g in prange(means2d.shape[0]):
        counts[g] = 0
        if radii[g, 0] <= 0 or radii[g, 1] <= 0:
            continue
        mx = means2d[g, 0] / ts
        my = means2d[g, 1] / ts
        rx = _F32(radii[g, 0]) / ts
        ry = _F32(radii[g, 1]) / ts
        x0 = int(min(max(math.floor(mx - rx), 0.0), tiles_x))
        y0 = int(min(max(math.floor(my - ry), 0.0), tiles_y))
        x1 = int(min(max(math.ceil(mx + rx), 0.0), tiles_x))
        y1 = int(min(max(math.ceil(my + ry), 0.0), tiles_y))
        box[g, 0] = x0
        box[g, 1] = y0
        box[g, 2] = x1
        box[g, 3] = y1
        if x1 > x0 and y1 > y0:
            counts[g] = (x1 - x0) * (y1 - y0)


@njit(cache=True)
def _fill(order, box, counts, tiles_x, n_tiles):  # pragma: no cover - numba
    """Counting sort of the depth-ordered Gaussians into per-tile lists (each list stays front to back)."""
    offsets = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        for ty in range(box[g, 1], box[g, 3]):
            for tx in range(box[g, 0], box[g, 2]):
                offsets[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    ids = np.empty(offsets[n_tiles], np.int32)
    cursor = offsets[:n_tiles].copy()
    for g in order:
        for ty in range(box[g, 1], box[g, 3]):
            row = ty * tiles_x
            for tx in range(box[g, 0], box[g, 2]):
                t = row + tx
                ids[cursor[t]] = g
                cursor[t] += 1
    return offsets, ids


def _bin(means2d, radii, depths, tile_size, tiles_x, tiles_y):
    """Per-tile depth-sorted Gaussian lists: (offsets [n_tiles + 1] int64, ids [n_isects] int32).

    Visible Gaussians are sorted once by the 64-bit key (depth bits, index): non-negative float32
    depths order like their bit patterns, and the index breaks ties as a stable sort would. numpy's
    sort of integer keys is several times faster than an argsort of floats.
    """
    n = means2d.shape[0]
    box = np.empty((n, 4), np.int32)
    counts = np.empty(n, np.int64)
    if n:
        _boxes(means2d, radii, tile_size, tiles_x, tiles_y, box, counts)
    vis = np.flatnonzero(counts)
    zv = depths[vis]
    zb = np.where(zv > 0, zv, np.float32(0.0)).view(np.uint32).astype(np.uint64)  # no -0.0
    keys = (zb << np.uint64(32)) | vis.astype(np.uint64)
    keys.sort()
    order = (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)
    return _fill(order, box, counts, tiles_x, tiles_x * tiles_y)


def _tile_schedule(offsets: np.ndarray) -> np.ndarray:
    """Non-empty tiles, most intersections first (workers take them round-robin)."""
    counts = np.diff(offsets)  # [n_tiles]
    nonempty = np.flatnonzero(counts)
    return nonempty[np.argsort(-counts[nonempty], kind="stable")].astype(np.int64)


@njit(inline="always", cache=True)
def _tile_pixels(px, py, T, act, x_0, y_0, ts, width, height, on, off):  # pragma: no cover - numba
    """Pixel centres of one tile in column-block order p = (cb * ts + row) * 8 + lane (8 columns per
    block), T = 1, act = on inside the image else off; returns the number of pixels inside."""
    n_in = 0
    for p in range(ts * ts):
        lane = p % _LANES
        rest = p // _LANES
        row = rest % ts
        cb = rest // ts
        xx = x_0 + cb * _LANES + lane
        yy = y_0 + row
        px[p] = _F32(xx) + _HALF
        py[p] = _F32(yy) + _HALF
        T[p] = _ONE
        inside = (xx < width) and (yy < height)
        act[p] = on if inside else off
        n_in += 1 if inside else 0
    return n_in


@njit(parallel=True, fastmath=_FM, cache=True)
def _forward_render(means2d, conics, colors, opac, depths, radii, offsets, ids, tiles, n_workers, tile_size,
                    tiles_x, width, height, out_rgb, out_alpha, out_depth):  # pragma: no cover - numba
    """Composite every listed tile: colour, alpha and sum z*w, with no bookkeeping for a backward pass."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        px = np.empty(npix, np.float32)
        py = np.empty(npix, np.float32)
        T = np.empty(npix, np.float32)
        ar = np.zeros(npix, np.float32)
        ag = np.zeros(npix, np.float32)
        ab = np.zeros(npix, np.float32)
        ad = np.zeros(npix, np.float32)
        act = np.empty(npix, np.float32)  # 1 while the pixel is still compositing, else 0
        for k in range(w, n_sched, n_workers):
            t = tiles[k]
            tyi = t // tiles_x
            x_0 = (t - tyi * tiles_x) * ts
            y_0 = tyi * ts
            n_act = _tile_pixels(px, py, T, act, x_0, y_0, ts, width, height, _ONE, _ZERO)
            ar[:] = _ZERO
            ag[:] = _ZERO
            ab[:] = _ZERO
            ad[:] = _ZERO
            for j in range(offsets[t], offsets[t + 1]):
                if n_act == 0:
                    break
                g = ids[j]
                r0, r1 = _span(means2d[g, 1], radii[g, 1], y_0, ts)
                c0, c1 = _span(means2d[g, 0], radii[g, 0], x_0, ts)
                if r1 <= r0 or c1 <= c0:
                    continue
                mx = means2d[g, 0]
                my = means2d[g, 1]
                ha = _HALF * conics[g, 0]
                cb = conics[g, 1]
                hc = _HALF * conics[g, 2]
                o = opac[g]
                cr = colors[g, 0]
                cg = colors[g, 1]
                cbl = colors[g, 2]
                z = depths[g]
                n_stop = _ZERO  # float32 counter keeps the loop in 8-wide float vectors
                for blk in range(c0 // _LANES, (c1 - 1) // _LANES + 1):
                    lo = (blk * ts + r0) * _LANES
                    ulo = np.uint64(lo)
                    # rows r0..r1 of one 8-column block; unsigned indices: numba's negative-index
                    # wraparound would stop vectorisation
                    for q in range((r1 - r0) * _LANES):
                        p = ulo + np.uint64(q)
                        dx = mx - px[p]
                        dy = my - py[p]
                        sig = ha * dx * dx + hc * dy * dy + cb * dx * dy
                        al = min(_ALPHA_MAX, o * _exp_neg(sig))
                        ok = (act[p] > _ZERO) & (sig >= _ZERO) & (al >= _ALPHA_MIN)
                        Tp = T[p]
                        nT = Tp * (_ONE - al)
                        stop = ok & (nT <= _T_EPS)
                        use = ok & (nT > _T_EPS)
                        wt = al * Tp if use else _ZERO
                        ar[p] += wt * cr
                        ag[p] += wt * cg
                        ab[p] += wt * cbl
                        ad[p] += wt * z
                        # unconditional stores of selected values: conditional ones become masked
                        # stores, which are very slow on some x86 cores
                        T[p] = Tp * ((_ONE - al) if use else _ONE)
                        act[p] = act[p] * (_ZERO if stop else _ONE)
                        n_stop += _ONE if stop else _ZERO
                n_act -= int(n_stop)
            for p in range(npix):
                lane = p % _LANES
                rest = p // _LANES
                yy = y_0 + rest % ts
                xx = x_0 + (rest // ts) * _LANES + lane
                if xx < width and yy < height:
                    out_rgb[yy, xx, 0] = ar[p]
                    out_rgb[yy, xx, 1] = ag[p]
                    out_rgb[yy, xx, 2] = ab[p]
                    out_alpha[yy, xx] = _ONE - T[p]
                    out_depth[yy, xx] = ad[p]


@njit(parallel=True, fastmath=_FM, cache=True)
def _forward_train(means2d, conics, colors, opac, depths, radii, offsets, ids, tiles, n_workers, tile_size,
                   tiles_x, width, height, out_rgb, out_alpha, out_depth, out_T, out_last,
                   out_n):  # pragma: no cover - numba
    """As :func:`_forward_render`, and saves per pixel the final transmittance and ``last``: the tile-list
    position of the Gaussian at which the pixel stopped (or the list length), so that exactly the
    Gaussians before ``last`` with alpha >= 1/255 were composited; out_n[w]: the number of
    Gaussian-pixel pairs composited by worker w (for the benchmark)."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        px = np.empty(npix, np.float32)
        py = np.empty(npix, np.float32)
        T = np.empty(npix, np.float32)
        ar = np.zeros(npix, np.float32)
        ag = np.zeros(npix, np.float32)
        ab = np.zeros(npix, np.float32)
        ad = np.zeros(npix, np.float32)
        # list position of the Gaussian where the pixel stopped: _NEVER while it is compositing, -1
        # outside the image (one array for both, and min() rather than a conditional store, keep
        # the loop vectorised)
        act = np.empty(npix, np.float32)
        n_pairs = 0.0
        for k in range(w, n_sched, n_workers):
            t = tiles[k]
            tyi = t // tiles_x
            x_0 = (t - tyi * tiles_x) * ts
            y_0 = tyi * ts
            start = offsets[t]
            n_act = _tile_pixels(px, py, T, act, x_0, y_0, ts, width, height, _NEVER, -_ONE)
            ar[:] = _ZERO
            ag[:] = _ZERO
            ab[:] = _ZERO
            ad[:] = _ZERO
            for j in range(start, offsets[t + 1]):
                if n_act == 0:
                    break
                g = ids[j]
                r0, r1 = _span(means2d[g, 1], radii[g, 1], y_0, ts)
                c0, c1 = _span(means2d[g, 0], radii[g, 0], x_0, ts)
                if r1 <= r0 or c1 <= c0:
                    continue
                mx = means2d[g, 0]
                my = means2d[g, 1]
                ha = _HALF * conics[g, 0]
                cb = conics[g, 1]
                hc = _HALF * conics[g, 2]
                o = opac[g]
                cr = colors[g, 0]
                cg = colors[g, 1]
                cbl = colors[g, 2]
                z = depths[g]
                jl = _F32(j - start)
                n_stop = _ZERO
                n_use = _ZERO
                for blk in range(c0 // _LANES, (c1 - 1) // _LANES + 1):
                    ulo = np.uint64((blk * ts + r0) * _LANES)
                    for q in range((r1 - r0) * _LANES):
                        p = ulo + np.uint64(q)
                        dx = mx - px[p]
                        dy = my - py[p]
                        sig = ha * dx * dx + hc * dy * dy + cb * dx * dy
                        al = min(_ALPHA_MAX, o * _exp_neg(sig))
                        ok = (act[p] > jl) & (sig >= _ZERO) & (al >= _ALPHA_MIN)
                        Tp = T[p]
                        nT = Tp * (_ONE - al)
                        stop = ok & (nT <= _T_EPS)
                        use = ok & (nT > _T_EPS)
                        wt = al * Tp if use else _ZERO
                        ar[p] += wt * cr
                        ag[p] += wt * cg
                        ab[p] += wt * cbl
                        ad[p] += wt * z
                        T[p] = Tp * ((_ONE - al) if use else _ONE)
                        act[p] = min(act[p], jl if stop else _NEVER)
                        n_use += _ONE if use else _ZERO
                        n_stop += _ONE if stop else _ZERO
                n_act -= int(n_stop)
                n_pairs += n_use
            n_list = _F32(offsets[t + 1] - start)
            for p in range(npix):
                lane = p % _LANES
                rest = p // _LANES
                yy = y_0 + rest % ts
                xx = x_0 + (rest // ts) * _LANES + lane
                if xx < width and yy < height:
                    out_rgb[yy, xx, 0] = ar[p]
                    out_rgb[yy, xx, 1] = ag[p]
                    out_rgb[yy, xx, 2] = ab[p]
                    out_alpha[yy, xx] = _ONE - T[p]
                    out_depth[yy, xx] = ad[p]
                    out_T[yy, xx] = T[p]
                    out_last[yy, xx] = np.int32(min(n_list, act[p]))
        out_n[w] = n_pairs


@njit(parallel=True, fastmath=_FM, cache=True)
def _backward(means2d, conics, colors, opac, depths, radii, offsets, ids, tiles, n_workers, tile_size, tiles_x,
              width, height, T_final, n_last, g_rgb, g_alpha, g_depth, out_grad):  # pragma: no cover
    """Back-to-front pass; writes d loss / d (2D Gaussian parameters) per intersection into out_grad
    (rows of intersections that touch no pixel are left as they are: zero)."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        px = np.empty(npix, np.float32)
        py = np.empty(npix, np.float32)
        T = np.empty(npix, np.float32)
        Q = np.empty(npix, np.float32)  # sum over later Gaussians of q_j w_j
        gat = np.empty(npix, np.float32)  # dL/dalpha * T_final
        gr = np.empty(npix, np.float32)
        gg = np.empty(npix, np.float32)
        gb = np.empty(npix, np.float32)
        gd = np.empty(npix, np.float32)
        lastp = np.empty(npix, np.float32)
        for k in range(w, n_sched, n_workers):
            t = tiles[k]
            tyi = t // tiles_x
            x_0 = (t - tyi * tiles_x) * ts
            y_0 = tyi * ts
            start = offsets[t]
            max_last = 0
            for p in range(npix):
                lane = p % _LANES
                rest = p // _LANES
                yy = y_0 + rest % ts
                xx = x_0 + (rest // ts) * _LANES + lane
                px[p] = _F32(xx) + _HALF
                py[p] = _F32(yy) + _HALF
                Q[p] = _ZERO
                if xx < width and yy < height:
                    T[p] = T_final[yy, xx]
                    lastp[p] = _F32(n_last[yy, xx])
                    gat[p] = g_alpha[yy, xx] * T_final[yy, xx]
                    gr[p] = g_rgb[yy, xx, 0]
                    gg[p] = g_rgb[yy, xx, 1]
                    gb[p] = g_rgb[yy, xx, 2]
                    gd[p] = g_depth[yy, xx]
                    max_last = max(max_last, n_last[yy, xx])
                else:
                    T[p] = _ONE
                    lastp[p] = _ZERO
                    gat[p] = _ZERO
                    gr[p] = _ZERO
                    gg[p] = _ZERO
                    gb[p] = _ZERO
                    gd[p] = _ZERO
            for jl64 in range(max_last - 1, -1, -1):
                j = start + jl64
                g = ids[j]
                r0, r1 = _span(means2d[g, 1], radii[g, 1], y_0, ts)
                c0, c1 = _span(means2d[g, 0], radii[g, 0], x_0, ts)
                if r1 <= r0 or c1 <= c0:
                    continue
                jl = _F32(jl64)
                mx = means2d[g, 0]
                my = means2d[g, 1]
                ca = conics[g, 0]
                cb = conics[g, 1]
                cc = conics[g, 2]
                o = opac[g]
                cr = colors[g, 0]
                cg = colors[g, 1]
                cbl = colors[g, 2]
                z = depths[g]
                s_dx = _ZERO  # sums of dL/dsigma times dx, dy, dx^2, dx dy, dy^2
                s_dy = _ZERO
                s_xx = _ZERO
                s_xy = _ZERO
                s_yy = _ZERO
                s_o = _ZERO
                s_r = _ZERO
                s_g = _ZERO
                s_b = _ZERO
                s_z = _ZERO
                for blk in range(c0 // _LANES, (c1 - 1) // _LANES + 1):
                    ulo = np.uint64((blk * ts + r0) * _LANES)
                    for qq in range((r1 - r0) * _LANES):
                        p = ulo + np.uint64(qq)
                        dx = mx - px[p]
                        dy = my - py[p]
                        sig = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        e = _exp_neg(sig)
                        v = o * e
                        al = min(_ALPHA_MAX, v)
                        ok = (jl < lastp[p]) & (sig >= _ZERO) & (al >= _ALPHA_MIN)
                        inv = _ONE / (_ONE - al)
                        Tp = T[p]
                        Ti = Tp * inv
                        wt = al * Ti if ok else _ZERO
                        q = gr[p] * cr + gg[p] * cg + gb[p] * cbl + gd[p] * z
                        dlda = Ti * q - (Q[p] - gat[p]) * inv
                        dlda = dlda if (ok & (v <= _ALPHA_MAX)) else _ZERO
                        dls = -v * dlda  # d loss / d sigma
                        s_r += wt * gr[p]
                        s_g += wt * gg[p]
                        s_b += wt * gb[p]
                        s_z += wt * gd[p]
                        s_o += e * dlda
                        s_dx += dls * dx
                        s_dy += dls * dy
                        s_xx += dls * dx * dx
                        s_xy += dls * dx * dy
                        s_yy += dls * dy * dy
                        Q[p] += q * wt
                        T[p] = Tp * (inv if ok else _ONE)
                out_grad[j, 0] = ca * s_dx + cb * s_dy
                out_grad[j, 1] = cb * s_dx + cc * s_dy
                out_grad[j, 2] = _HALF * s_xx
                out_grad[j, 3] = s_xy
                out_grad[j, 4] = _HALF * s_yy
                out_grad[j, 5] = s_o
                out_grad[j, 6] = s_r
                out_grad[j, 7] = s_g
                out_grad[j, 8] = s_b
                out_grad[j, 9] = s_z


@njit(cache=True)
def _reduce(ids, grad_isect, n):  # pragma: no cover - numba
    """Sum per-intersection gradients [M, 10] into per-Gaussian gradients [n, 10]."""
    out = np.zeros((n, grad_isect.shape[1]), np.float32)
    for j in range(ids.shape[0]):
        g = ids[j]
        for c in range(grad_isect.shape[1]):
            out[g, c] += grad_isect[j, c]
    return out


def _n_workers() -> int:
    return max(1, min(numba.get_num_threads(), torch.get_num_threads()))


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).numpy())


def _prepare(means2d, conics, colors, opacities, depths, radii, width, height, tile_size):
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    m2 = _np32(means2d)  # [N, 2]
    r2 = np.ascontiguousarray(radii.detach().to(torch.int32).numpy())  # [N, 2]
    z = _np32(depths)  # [N]
    offsets, ids = _bin(m2, r2, z, tile_size, tiles_x, tiles_y)
    tiles = _tile_schedule(offsets)
    arrays = (m2, _np32(conics), _np32(colors), _np32(opacities), z, r2)
    return arrays, offsets, ids, tiles, tiles_x


def _render(arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, save: bool, count: bool = False):
    rgb = np.zeros((height, width, 3), np.float32)
    alpha = np.zeros((height, width), np.float32)
    dsum = np.zeros((height, width), np.float32)
    if not save:
        if tiles.size:
            _forward_render(*arrays, offsets, ids, tiles, _n_workers(), tile_size, tiles_x, width, height,
                            rgb, alpha, dsum)
        return rgb, alpha, dsum, None, None
    T = np.ones((height, width), np.float32)
    last = np.zeros((height, width), np.int32)
    nw = _n_workers()
    n_pairs = np.zeros(nw, np.float64)
    if tiles.size:
        _forward_train(*arrays, offsets, ids, tiles, nw, tile_size, tiles_x, width, height,
                       rgb, alpha, dsum, T, last, n_pairs)
    if count:  # the number of Gaussian-pixel pairs composited
        return rgb, alpha, dsum, T, last, int(n_pairs.sum())
    return rgb, alpha, dsum, T, last


class _CompositeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, tile_size):
        arrays, offsets, ids, tiles, tiles_x = _prepare(
            means2d, conics, colors, opacities, depths, radii, width, height, tile_size
        )
        rgb, alpha, dsum, T, last = _render(arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, True)
        ctx.saved = (arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, T, last)
        ctx.n = means2d.shape[0]
        dt = means2d.dtype
        return (torch.from_numpy(rgb).to(dt), torch.from_numpy(alpha)[..., None].to(dt),
                torch.from_numpy(dsum)[..., None].to(dt))

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth):
        arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, T, last = ctx.saved
        n = ctx.n
        grad_isect = np.zeros((ids.shape[0], _NGRAD), np.float32)
        if tiles.size:
            _backward(*arrays, offsets, ids, tiles, _n_workers(), tile_size, tiles_x, width, height, T, last,
                      _np32(g_rgb), _np32(g_alpha[..., 0]), _np32(g_depth[..., 0]), grad_isect)
        g = torch.from_numpy(_reduce(ids, grad_isect, n))  # [N, 10]
        dt = g_rgb.dtype
        return (g[:, 0:2].to(dt), g[:, 2:5].to(dt), g[:, 6:9].to(dt), g[:, 5].to(dt), g[:, 9].to(dt),
                None, None, None, None)


def composite_cpu(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    colors: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N, 2] int32, 0 = culled
    width: int,
    height: int,
    tile_size: int = 16,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite projected Gaussians with the numba kernels: colour [H, W, 3], alpha [H, W, 1], sum z*w [H, W, 1].

    Same rules and outputs as :func:`plantsplat.raster.reference.composite_reference`; differentiable
    with respect to means2d, conics, colors, opacities and depths.

    Example:
        >>> c, a, d = composite_cpu(torch.tensor([[4.0, 4.0]]), torch.tensor([[1.0, 0.0, 1.0]]),
        ...     torch.ones(1, 3), torch.tensor([0.5]), torch.tensor([2.0]), torch.tensor([[3, 3]]), 8, 8)
        >>> round(float(a[3, 3, 0]), 4)  # 0.5 * exp(-0.5 * (0.5^2 + 0.5^2)) at pixel centre (3.5, 3.5)
        0.3894
    """
    if tile_size % _LANES:
        from . import RasterInputError

        raise RasterInputError(f"rasterize: the cpu backend needs tile_size to be a multiple of {_LANES}, got {tile_size}")
    inputs = (means2d, conics, colors, opacities, depths)
    if torch.is_grad_enabled() and any(t.requires_grad for t in inputs):
        return _CompositeCPU.apply(means2d, conics, colors, opacities, depths, radii, width, height, tile_size)
    arrays, offsets, ids, tiles, tiles_x = _prepare(
        means2d, conics, colors, opacities, depths, radii, width, height, tile_size
    )
    rgb, alpha, dsum, _, _ = _render(arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, False)
    dt = means2d.dtype
    return (torch.from_numpy(rgb).to(dt), torch.from_numpy(alpha)[..., None].to(dt),
            torch.from_numpy(dsum)[..., None].to(dt))

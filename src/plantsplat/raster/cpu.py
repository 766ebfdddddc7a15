"""CPU backend: tile-parallel numba kernels for compositing, with a hand-written backward pass.

Projection and SH colours have their own numba kernels (:mod:`plantsplat.raster.cpu_projection`,
:mod:`plantsplat.raster.sh_cpu`); this module composites the projected 2D Gaussians, which is where
most of the time goes. The steps, all in float32:

1. ``_records``: one 64-byte row per Gaussian with everything the tile kernels read (mean, conic,
   opacity, colour, depth, and the extent of the ellipse outside which alpha < 1/255), so a
   tile-list entry costs one cache line rather than one in each of six arrays.
2. ``_bin``: tile boxes (gsplat's box from the screen radii, less the tiles the alpha >= 1/255
   ellipse's extent misses), visible Gaussians put in depth order once (equal depths in index order;
   :mod:`plantsplat.raster.cpu_order`), then a counting sort into per-tile lists, so each tile's list
   is front to back.
3. ``_forward_render`` / ``_forward_train``: parallel over workers, each taking runs of 8
   non-empty tiles in raster order from a shared atomic counter (a worker slowed by other load
   takes fewer; neighbouring tiles share Gaussians and run on the same core); within a tile, the
   list's records are gathered 64 at a time into a small buffer (independent loads, so their cache
   misses overlap; the next 64 are prefetched while these composite), then composited one Gaussian
   at a time in depth order,
   vectorised over 8-pixel column blocks: the tile's pixels are stored block by block
   (``p = (block * ts + row) * 8 + lane``), and in each block only the rows the Gaussian's
   alpha >= 1/255 ellipse reaches there are visited (``_block_rows``: exact, slightly widened), as
   contiguous runs of whole vectors. A tile stops once every pixel's transmittance has reached the
   stop threshold. The train variant also saves per pixel the final transmittance and the list
   position where the pixel stopped.
4. ``_backward``: the same tiles and rows back to front, recovering each Gaussian's transmittance by
   division; gradients are written per (tile, Gaussian) intersection (no atomics, no races,
   deterministic) and summed per Gaussian afterwards (``_reduce``).

The culling only skips pixels where alpha < 1/255, which the compositing rule skips anyway, so the
images and gradients are those of the reference (gsplat's rules); tests check the culling region
against brute force. Under ``torch.no_grad()`` (or when no input needs a gradient) only ``_bin``
and ``_forward_render`` run and nothing is kept.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from llvmlite import ir as _ir
from numba import njit, prange
from numba import types as _nt
from numba.core import cgutils as _cg
from numba.extending import intrinsic
from torch import Tensor

from plantsplat.raster.numba_config import FASTMATH  # (also numba's threading layer)

from . import RasterInputError
from .cpu_order import depth_order


@intrinsic
def _prefetch(typingctx, arr, idx):  # pragma: no cover - numba
    """Ask the CPU to fetch the cache line of arr[idx] (1D array) ahead of use; no bounds check needed
    (a prefetch never faults)."""
    if not isinstance(arr, _nt.Array) or arr.ndim != 1 or not isinstance(idx, _nt.Integer):
        return None

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = _cg.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i32 = _ir.IntType(32)
        fn = _cg.get_or_insert_function(builder.module, _ir.FunctionType(_ir.VoidType(), [ptr.type, i32, i32, i32]),
                                        "llvm.prefetch.p0")
        builder.call(fn, [ptr, _ir.Constant(i32, 0), _ir.Constant(i32, 3), _ir.Constant(i32, 1)])  # read, keep
        return context.get_dummy_value()

    return _nt.void(arr, idx), codegen


@intrinsic
def _fetch_add(typingctx, arr, idx, val):  # pragma: no cover - numba
    """Atomic ``old = arr[idx]; arr[idx] += val; return old`` on an int64 1D array (the workers' shared
    tile counter)."""
    if not isinstance(arr, _nt.Array) or arr.ndim != 1 or arr.dtype != _nt.int64:
        return None

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = _cg.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        v = context.cast(builder, args[2], signature.args[2], _nt.int64)
        return builder.atomic_rmw("add", ptr, v, "monotonic")

    return _nt.int64(arr, idx, val), codegen


_F32 = np.float32
_ZERO = _F32(0.0)
_HALF = _F32(0.5)
_ONE = _F32(1.0)
_ALPHA_MAX = _F32(0.999)
_ALPHA_MIN = _F32(1.0 / 255.0)
_T_EPS = _F32(1e-4)
# fast-math without the no-NaN/no-Inf assumptions (inputs are validated, but be safe)
_FM = set(FASTMATH)
_NGRAD = 10  # per-intersection gradient: mean x, mean y, conic a, b, c, opacity, r, g, b, depth
_LANES = 8  # pixel loops run over 8-column blocks (one AVX2 float32 vector); tile_size is a multiple
_SIG_MAX = _F32(6.0)  # exp(-6) < 1/255: larger sigma can never give a visible alpha
# exp(-x) ~ sum_k _EXP_C[k] x^k on [0, 0.75] (see _exp_neg)
_EXP_C = (_ONE, _F32(-0.9999997019767761), _F32(0.4999932646751404), _F32(-0.1666114628314972),
          _F32(0.04145379737019539), _F32(-0.007908405736088753), _F32(0.0009540405590087175))
_TWO = _F32(2.0)
_NEVER = _F32(2.0**30)  # larger than any tile-list position (float32-exact)
_FOUR = _F32(4.0)
_BIG = _F32(1e30)
_NREC = 16  # floats per Gaussian record (_records): one 64-byte cache line
_CH = 64  # records gathered at a time from a tile list (_gather)
_RUN = 8  # tiles a worker takes at a time from the shared counter
_CHECK = 16  # Gaussians between the render kernel's checks whether a whole tile has stopped
_TS_MAX = 32  # largest tile edge the cpu kernels take
# per-pixel arrays of a worker lie in one allocation, this many floats apart (> _TS_MAX^2, and not a
# multiple of 1024 floats, so no two of them share 4 KiB address bits); see _scratch
_STRIDE = _TS_MAX * _TS_MAX + 16


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
def _floor_in(x, lo, hi):  # pragma: no cover - numba
    """floor(x) clamped to the ints [lo, hi], for any float32 x, without a libm call."""
    y = min(max(x, _F32(lo - 1)), _F32(hi + 1))
    i = int(y)
    i -= 1 if _F32(i) > y else 0
    return min(max(i, lo), hi)


@njit(inline="always", cache=True)
def _span(m, r, ts):  # pragma: no cover - numba
    """Tile-local pixel range [lo, hi) (clamped to [0, ts]) whose centres i + 0.5 lie in [m - r, m + r]."""
    return -_floor_in(r + _HALF - m, -ts, 0), _floor_in(m + r - _HALF, -1, ts - 1) + 1


@njit(inline="always", fastmath=_FM, cache=True)
def _block_rows(mx, my, blk, xt0, sl, Q, S, r0, r1, ts):  # pragma: no cover - numba
    """Rows [lo, hi) within [r0, r1) that the Gaussian's level ellipse reaches in one 8-column block.

    The ellipse ``sigma <= s`` (tile-local centre mx, my; see :func:`_records`) meets the block's
    columns for dx = mx - x in [u0, u1]. For a fixed dx its dy = my - y range is
    ``sl dx -+ sqrt(S - Q dx^2)``; the upper end is concave in dx with its maximum at the ellipse's
    top point dx = xt0 and the lower end mirrors it (bottom point -xt0), so clamping those points to
    [u0, u1] gives the exact dy range over the block. Row centres are widened by 0.01 px.
    """
    u1 = mx - (_F32(blk * _LANES) + _HALF)
    u0 = u1 - _F32(_LANES - 1)
    xt = min(max(xt0, u0), u1)
    xb = min(max(-xt0, u0), u1)
    dyh = sl * xt + math.sqrt(max(S - xt * xt * Q, _ZERO))
    dyl = sl * xb - math.sqrt(max(S - xb * xb * Q, _ZERO))
    lo = max(-_floor_in(dyh + _F32(0.51) - my, -ts, 0), r0)
    hi = min(_floor_in(my - dyl - _F32(0.49), -1, ts - 1) + 1, r1)
    return lo, hi


@njit(parallel=True, fastmath=_FM, cache=True)
def _records(means2d, conics, colors, opac, depths, radii, rec):  # pragma: no cover - numba
    """One 64-byte row per Gaussian with everything the tile kernels read, so that a tile list costs one
    cache line per entry (instead of one in each of six arrays):

    0-1 mean x, y; 2-4 conic a/2, b, c/2; 5 opacity; 6-8 colour; 9 depth; 10-11 half extents X, Y of
    the ellipse outside which alpha < 1/255 (never more than the screen radii); 12-15 the block-row
    culling constants of :func:`_block_rows` (top point dx, dy-centre slope, Q, S).

    The level is s = ln(255 opacity), widened by 1e-3 plus 2e-6 times the size of sigma's terms on
    the ellipse (float32 rounding of sigma in the kernels), so every pixel the kernels could give
    alpha >= 1/255 lies inside. Degenerate conics fall back to the screen radii and no row culling.
    """
    for g in prange(means2d.shape[0]):
        ha = _HALF * conics[g, 0]
        cb = conics[g, 1]
        hc = _HALF * conics[g, 2]
        o = opac[g]
        rec[g, 0] = means2d[g, 0]
        rec[g, 1] = means2d[g, 1]
        rec[g, 2] = ha
        rec[g, 3] = cb
        rec[g, 4] = hc
        rec[g, 5] = o
        rec[g, 6] = colors[g, 0]
        rec[g, 7] = colors[g, 1]
        rec[g, 8] = colors[g, 2]
        rec[g, 9] = depths[g]
        D = _FOUR * ha * hc - cb * cb  # determinant of the conic
        s = math.log(max(o * _F32(255.0), _ONE))
        rx = _F32(radii[g, 0])
        ry = _F32(radii[g, 1])
        if D > _ZERO and ha > _ZERO and hc > _ZERO and s > _ZERO:
            X = math.sqrt(_FOUR * s * hc / D)
            Y = math.sqrt(_FOUR * s * ha / D)
            size = (ha + _HALF * abs(cb)) * X * X + (hc + _HALF * abs(cb)) * Y * Y
            s2 = s + _F32(1e-3) + _F32(2e-6) * size
            X = math.sqrt(_FOUR * s2 * hc / D) + _F32(1e-3)
            Y = math.sqrt(_FOUR * s2 * ha / D) + _F32(1e-3)
            rec[g, 10] = min(X, rx)
            rec[g, 11] = min(Y, ry)
            rec[g, 12] = -cb / (_TWO * ha) * Y
            rec[g, 13] = -cb / (_TWO * hc)
            rec[g, 14] = D / (_FOUR * hc * hc)
            rec[g, 15] = s2 / hc
        else:
            rec[g, 10] = rx
            rec[g, 11] = ry
            rec[g, 12] = _ZERO
            rec[g, 13] = _ZERO
            rec[g, 14] = _ZERO
            rec[g, 15] = _BIG


@njit(parallel=True, cache=True)
def _boxes(rec, radii, tile_size, tiles_x, tiles_y, box, counts):  # pragma: no cover - numba
    """Tile box [x0, y0, x1, y1) of every Gaussian and its tile count: gsplat's box from the screen radii,
    less the tiles none of whose pixel centres lies within the half extents X, Y (alpha < 1/255 there)."""
    ts = _F32(tile_size)
    for g in prange(rec.shape[0]):
        counts[g] = 0
        if radii[g, 0] <= 0 or radii[g, 1] <= 0:
            continue
        mx = rec[g, 0]
        my = rec[g, 1]
        rx = _F32(radii[g, 0]) / ts
        ry = _F32(radii[g, 1]) / ts
        ex = rec[g, 10]
        ey = rec[g, 11]
        # gsplat's box, floor(m / ts - r / ts) .. ceil(m / ts + r / ts) as the reference's tile_boxes,
        # and the tiles with a pixel centre in [m - e, m + e] (0.01 px wider): ceil(a - 1) .. floor(b) + 1
        x0 = max(_floor_in(mx / ts - rx, 0, tiles_x), -_floor_in(_ONE - (mx - ex + _F32(0.49)) / ts, -tiles_x, 0))
        y0 = max(_floor_in(my / ts - ry, 0, tiles_y), -_floor_in(_ONE - (my - ey + _F32(0.49)) / ts, -tiles_y, 0))
        x1 = min(-_floor_in(-(mx / ts + rx), -tiles_x, 0), _floor_in((mx + ex - _F32(0.49)) / ts, -1, tiles_x - 1) + 1)
        y1 = min(-_floor_in(-(my / ts + ry), -tiles_y, 0), _floor_in((my + ey - _F32(0.49)) / ts, -1, tiles_y - 1) + 1)
        box[g, 0] = x0
        box[g, 1] = y0
        box[g, 2] = x1
        box[g, 3] = y1
        if x1 > x0 and y1 > y0:
            counts[g] = (x1 - x0) * (y1 - y0)


@njit(parallel=True, cache=True)
def _fill(order, box, tiles_x, n_tiles, n_chunks):  # pragma: no cover - numba
    """Counting sort of the depth-ordered Gaussians into per-tile lists (each list stays front to back).

    The boxes are first copied into depth order (one parallel gather, then both passes read them
    sequentially); the passes run in parallel over n_chunks consecutive runs of ``order``, a tile's
    entries from an earlier run placed first, so the lists stay in depth order."""
    n = order.shape[0]
    bo = np.empty((n, 4), np.int32)
    for k in prange(n):
        g = order[k]
        for f in range(4):
            bo[k, f] = box[g, f]
    cnt = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for k in range(n * c // n_chunks, n * (c + 1) // n_chunks):
            for ty in range(bo[k, 1], bo[k, 3]):
                for tx in range(bo[k, 0], bo[k, 2]):
                    cnt[c, ty * tiles_x + tx] += 1
    offsets = np.empty(n_tiles + 1, np.int64)
    acc = 0
    for t in range(n_tiles):
        offsets[t] = acc
        for c in range(n_chunks):
            m = cnt[c, t]
            cnt[c, t] = acc  # now chunk c's write cursor in tile t
            acc += m
    offsets[n_tiles] = acc
    ids = np.empty(acc, np.int32)
    for c in prange(n_chunks):
        for k in range(n * c // n_chunks, n * (c + 1) // n_chunks):
            g = order[k]
            for ty in range(bo[k, 1], bo[k, 3]):
                row = ty * tiles_x
                for tx in range(bo[k, 0], bo[k, 2]):
                    t = row + tx
                    ids[cnt[c, t]] = g
                    cnt[c, t] += 1
    return offsets, ids


def _bin(rec, radii, depths, tile_size, tiles_x, tiles_y):
    """Per-tile depth-sorted Gaussian lists: (offsets [n_tiles + 1] int64, ids [n_isects] int32).

    Visible Gaussians are put in depth order once (:func:`~plantsplat.raster.cpu_order.depth_order`, a stable radix
    sort: equal depths in index order), then counted into the tiles.
    """
    n = rec.shape[0]
    box = np.empty((n, 4), np.int32)
    counts = np.zeros(n, np.int64)
    if n:
        _boxes(rec, radii, tile_size, tiles_x, tiles_y, box, counts)
    return _fill(depth_order(depths, counts), box, tiles_x, tiles_x * tiles_y, _n_workers())


@njit(parallel=True, cache=True)
def _trim_tails(offsets, ids, first_bg):  # pragma: no cover - numba
    """Tile lists without their trailing entries ``>= first_bg`` (Gaussians in the background colour
    with nothing but such Gaussians behind them): new (offsets, ids)."""
    n_tiles = offsets.shape[0] - 1
    ends = np.empty(n_tiles, np.int64)
    for t in prange(n_tiles):
        e = offsets[t + 1]
        while e > offsets[t] and ids[e - 1] >= first_bg:
            e -= 1
        ends[t] = e
    new_off = np.empty(n_tiles + 1, np.int64)
    acc = 0
    for t in range(n_tiles):
        new_off[t] = acc
        acc += ends[t] - offsets[t]
    new_off[n_tiles] = acc
    new_ids = np.empty(acc, np.int32)
    for t in prange(n_tiles):
        o = new_off[t]
        for j in range(offsets[t], ends[t]):
            new_ids[o + j - offsets[t]] = ids[j]
    return new_off, new_ids


def _tile_schedule(offsets: np.ndarray) -> np.ndarray:
    """Non-empty tiles in raster order. Workers take runs of ``_RUN`` of them from a shared atomic
    counter (so a worker slowed by other load takes fewer), and neighbouring tiles, which share
    Gaussians, run one after the other on the same core."""
    return np.flatnonzero(np.diff(offsets)).astype(np.int64)


@njit(inline="always", cache=True)
def _local_pixels(px, py, ts):  # pragma: no cover - numba
    """Tile-local pixel centres in column-block order p = (block * ts + row) * 8 + lane."""
    for cbk in range(ts // _LANES):
        for row in range(ts):
            for lane in range(_LANES):
                p = (cbk * ts + row) * _LANES + lane
                px[p] = _F32(cbk * _LANES + lane) + _HALF
                py[p] = _F32(row) + _HALF


@njit(inline="always", cache=True)
def _scratch(n_fields):  # pragma: no cover - numba
    """A worker's zeroed per-pixel arrays as one allocation; :func:`_field` views one of them.

    The pixel loops read and write several such arrays. Held in separate allocations, LLVM cannot
    prove they do not overlap and checks at run time before every vectorised row run (dozens of
    pointer comparisons per Gaussian and block); as views at constant offsets of one allocation,
    it proves it at compile time."""
    return np.zeros(n_fields * _STRIDE, np.float32)


@njit(inline="always", cache=True)
def _field(work, f, npix):  # pragma: no cover - numba
    return work[f * _STRIDE:f * _STRIDE + npix]


@njit(inline="always", cache=True)
def _mark_inside(a, nx, ny, ts, on, off):  # pragma: no cover - numba
    """a[p] = on for the tile's pixels inside the image (nx columns, ny rows), off for the others."""
    if nx == ts and ny == ts:
        a[:] = on
        return
    for cbk in range(ts // _LANES):
        for row in range(ts):
            for lane in range(_LANES):
                inside = (cbk * _LANES + lane < nx) and (row < ny)
                a[(cbk * ts + row) * _LANES + lane] = on if inside else off


@njit(inline="always", cache=True)
def _gather(rec, ids, j, m, buf):  # pragma: no cover - numba
    """buf[i] = rec[ids[j + i]] for i < m: a short loop of independent loads, so the cache misses of
    the random rows overlap (the compositing loop between two list entries would serialise them)."""
    for i in range(m):
        g = ids[j + i]
        for f in range(_NREC):
            buf[i, f] = rec[g, f]


@njit(inline="always", cache=True)
def _all_stopped(T, npix):  # pragma: no cover - numba
    """Whether every pixel of the tile has stopped (the render kernel keeps stopped pixels' T negated)."""
    live = _ZERO
    for p in range(npix):
        live = max(live, T[p])
    return live <= _ZERO


@njit(inline="always", cache=True)
def _tile_origin(t, tiles_x, ts, width, height):  # pragma: no cover - numba
    """Pixel origin (x_0, y_0) of tile t and how many of its columns and rows (nx, ny) lie in the image."""
    tyi = t // tiles_x
    x_0 = (t - tyi * tiles_x) * ts
    y_0 = tyi * ts
    return x_0, y_0, min(ts, width - x_0), min(ts, height - y_0)


@njit(inline="always", cache=True)
def _unpack(buf, i, x_0, y_0, ts):  # pragma: no cover - numba
    """Record i of a gathered chunk (see :func:`_records`) for a tile at (x_0, y_0): the tile-local centre
    mx, my; the pixel rows [r0, r1) and columns [c0, c1) its half extents reach; conic a/2, b, c/2; opacity;
    colour; depth."""
    mx = buf[i, 0] - _F32(x_0)
    my = buf[i, 1] - _F32(y_0)
    r0, r1 = _span(my, buf[i, 11], ts)
    c0, c1 = _span(mx, buf[i, 10], ts)
    return (mx, my, r0, r1, c0, c1, buf[i, 2], buf[i, 3], buf[i, 4], buf[i, 5], buf[i, 6], buf[i, 7], buf[i, 8],
            buf[i, 9])


@njit(inline="always", cache=True)
def _prefetch_next(flat, ids, j, end, tiles, offsets, k, k_end):  # pragma: no cover - numba
    """Prefetch the records of the next chunk: list entries ``j ..`` of this tile (up to ``end``), or the first
    ones of tile ``tiles[k]`` when this tile's list is done."""
    if j < end:
        for jj in range(j, min(end, j + _CH)):
            _prefetch(flat, np.int64(ids[jj]) * _NREC)
    elif k < k_end:
        tn = tiles[k]
        for jj in range(offsets[tn], min(offsets[tn + 1], offsets[tn] + _CH)):
            _prefetch(flat, np.int64(ids[jj]) * _NREC)


@njit(parallel=True, fastmath=_FM, cache=True)
def _forward_render(rec, offsets, ids, tiles, n_workers, tile_size, tiles_x, width, height, out_rgb, out_alpha,
                    out_depth, counter):  # pragma: no cover - numba
    """Composite every listed tile: colour, alpha and sum z*w, with no bookkeeping for a backward pass.

    A pixel that stops keeps its transmittance negated (T < 0 means stopped; pixels outside the image
    start at -1), so one array does for both. Whether the whole tile has stopped is checked every
    ``_CHECK`` Gaussians, not counted in the pixel loop (which that count slowed by a fifth)."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        work = _scratch(7)
        px = _field(work, 0, npix)
        py = _field(work, 1, npix)
        _local_pixels(px, py, ts)
        T = _field(work, 2, npix)
        ar = _field(work, 3, npix)
        ag = _field(work, 4, npix)
        ab = _field(work, 5, npix)
        ad = _field(work, 6, npix)
        buf = np.empty((_CH, _NREC), np.float32)
        flat = rec.reshape(-1)  # for _prefetch
        k = 0
        k_end = 0
        while True:
            if k >= k_end:  # next run of tiles
                k = _fetch_add(counter, 0, _RUN)
                if k >= n_sched:
                    break
                k_end = min(k + _RUN, n_sched)
            t = tiles[k]
            x_0, y_0, nx, ny = _tile_origin(t, tiles_x, ts, width, height)
            _mark_inside(T, nx, ny, ts, _ONE, -_ONE)
            ar[:] = _ZERO
            ag[:] = _ZERO
            ab[:] = _ZERO
            ad[:] = _ZERO
            j = offsets[t]
            end = offsets[t + 1]
            done = False
            while j < end and not done:
                m = min(_CH, end - j)
                _gather(rec, ids, j, m, buf)
                # the next records of this list, or the first of the next tile's, while this chunk composites
                _prefetch_next(flat, ids, j + m, end, tiles, offsets, k + 1, k_end)
                j += m
                for i in range(m):
                    if i % _CHECK == _CHECK - 1 and _all_stopped(T, npix):
                        done = True
                        break
                    mx, my, r0, r1, c0, c1, ha, cb, hc, o, cr, cg, cbl, z = _unpack(buf, i, x_0, y_0, ts)
                    if r1 <= r0 or c1 <= c0:
                        continue
                    for blk in range(c0 // _LANES, (c1 - 1) // _LANES + 1):
                        b0, b1 = _block_rows(mx, my, blk, buf[i, 12], buf[i, 13], buf[i, 14], buf[i, 15], r0, r1, ts)
                        if b1 <= b0:
                            continue
                        # rows b0..b1 of one 8-column block; unsigned indices: numba's negative-index
                        # wraparound would stop vectorisation
                        ulo = np.uint64((blk * ts + b0) * _LANES)
                        for q in range((b1 - b0) * _LANES):
                            p = ulo + np.uint64(q)
                            dx = mx - px[p]
                            dy = my - py[p]
                            sig = ha * dx * dx + hc * dy * dy + cb * dx * dy
                            al = min(_ALPHA_MAX, o * _exp_neg(sig))
                            Tp = T[p]
                            ok = (Tp > _ZERO) & (sig >= _ZERO) & (al >= _ALPHA_MIN)
                            nT = Tp * (_ONE - al)
                            stop = ok & (nT <= _T_EPS)
                            use = ok & (nT > _T_EPS)
                            wt = al * Tp if use else _ZERO
                            ar[p] += wt * cr
                            ag[p] += wt * cg
                            ab[p] += wt * cbl
                            ad[p] += wt * z
                            # unconditional stores of plain products: selects nested in the stored
                            # value become masked stores, which are very slow on some x86 cores
                            f1 = (_ONE - al) if use else _ONE
                            sg = -_ONE if stop else _ONE
                            T[p] = Tp * f1 * sg
            for cbk in range(ts // _LANES):
                for row in range(ny):
                    for lane in range(min(_LANES, nx - cbk * _LANES)):
                        p = (cbk * ts + row) * _LANES + lane
                        yy = y_0 + row
                        xx = x_0 + cbk * _LANES + lane
                        out_rgb[yy, xx, 0] = ar[p]
                        out_rgb[yy, xx, 1] = ag[p]
                        out_rgb[yy, xx, 2] = ab[p]
                        out_alpha[yy, xx] = _ONE - abs(T[p])
                        out_depth[yy, xx] = ad[p]
            k += 1


@njit(parallel=True, fastmath=_FM, cache=True)
def _forward_train(rec, offsets, ids, tiles, n_workers, tile_size, tiles_x, width, height, out_rgb, out_alpha,
                   out_depth, out_T, out_last, out_n, counter):  # pragma: no cover - numba
    """As :func:`_forward_render`, and saves per pixel the final transmittance and ``last``: the tile-list
    position of the Gaussian at which the pixel stopped (or the list length), so that exactly the
    Gaussians before ``last`` with alpha >= 1/255 were composited; out_n[w]: the number of
    Gaussian-pixel pairs composited by worker w (for the benchmark)."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        work = _scratch(8)
        px = _field(work, 0, npix)
        py = _field(work, 1, npix)
        _local_pixels(px, py, ts)
        T = _field(work, 2, npix)
        ar = _field(work, 3, npix)
        ag = _field(work, 4, npix)
        ab = _field(work, 5, npix)
        ad = _field(work, 6, npix)
        # list position of the Gaussian where the pixel stopped: _NEVER while it is compositing, -1
        # outside the image. The pixel loop only negates a stopping pixel's T (as the render
        # kernel); the position is written after that Gaussian, when any pixel stopped. Written
        # in the loop, LLVM made it a masked store, which slowed the whole loop by a sixth.
        act = _field(work, 7, npix)
        buf = np.empty((_CH, _NREC), np.float32)
        flat = rec.reshape(-1)  # for _prefetch
        n_pairs = 0.0
        k = 0
        k_end = 0
        while True:
            if k >= k_end:  # next run of tiles
                k = _fetch_add(counter, 0, _RUN)
                if k >= n_sched:
                    break
                k_end = min(k + _RUN, n_sched)
            t = tiles[k]
            x_0, y_0, nx, ny = _tile_origin(t, tiles_x, ts, width, height)
            n_act = nx * ny
            start = offsets[t]
            end = offsets[t + 1]
            _mark_inside(act, nx, ny, ts, _NEVER, -_ONE)
            _mark_inside(T, nx, ny, ts, _ONE, -_ONE)
            ar[:] = _ZERO
            ag[:] = _ZERO
            ab[:] = _ZERO
            ad[:] = _ZERO
            j = start
            while j < end and n_act > 0:
                m = min(_CH, end - j)
                _gather(rec, ids, j, m, buf)
                # the next records of this list, or the first of the next tile's, while this chunk composites
                _prefetch_next(flat, ids, j + m, end, tiles, offsets, k + 1, k_end)
                for i in range(m):
                    if n_act == 0:
                        break
                    mx, my, r0, r1, c0, c1, ha, cb, hc, o, cr, cg, cbl, z = _unpack(buf, i, x_0, y_0, ts)
                    if r1 <= r0 or c1 <= c0:
                        continue
                    jl = _F32(j + i - start)
                    n_stop = _ZERO
                    n_use = _ZERO
                    for blk in range(c0 // _LANES, (c1 - 1) // _LANES + 1):
                        b0, b1 = _block_rows(mx, my, blk, buf[i, 12], buf[i, 13], buf[i, 14], buf[i, 15], r0, r1, ts)
                        if b1 <= b0:
                            continue
                        ulo = np.uint64((blk * ts + b0) * _LANES)
                        for q in range((b1 - b0) * _LANES):
                            p = ulo + np.uint64(q)
                            dx = mx - px[p]
                            dy = my - py[p]
                            sig = ha * dx * dx + hc * dy * dy + cb * dx * dy
                            al = min(_ALPHA_MAX, o * _exp_neg(sig))
                            Tp = T[p]
                            ok = (Tp > _ZERO) & (sig >= _ZERO) & (al >= _ALPHA_MIN)
                            nT = Tp * (_ONE - al)
                            stop = ok & (nT <= _T_EPS)
                            use = ok & (nT > _T_EPS)
                            wt = al * Tp if use else _ZERO
                            ar[p] += wt * cr
                            ag[p] += wt * cg
                            ab[p] += wt * cbl
                            ad[p] += wt * z
                            f1 = (_ONE - al) if use else _ONE
                            sg = -_ONE if stop else _ONE
                            T[p] = Tp * f1 * sg
                            n_use += _ONE if use else _ZERO
                            n_stop += _ONE if stop else _ZERO
                    if n_stop > _ZERO:  # rare: each pixel stops once
                        n_act -= int(n_stop)
                        for p in range(npix):
                            if T[p] < _ZERO and act[p] == _NEVER:
                                act[p] = jl
                    n_pairs += n_use
                j += m
            n_list = _F32(end - start)
            for cbk in range(ts // _LANES):
                for row in range(ny):
                    for lane in range(min(_LANES, nx - cbk * _LANES)):
                        p = (cbk * ts + row) * _LANES + lane
                        yy = y_0 + row
                        xx = x_0 + cbk * _LANES + lane
                        out_rgb[yy, xx, 0] = ar[p]
                        out_rgb[yy, xx, 1] = ag[p]
                        out_rgb[yy, xx, 2] = ab[p]
                        out_alpha[yy, xx] = _ONE - abs(T[p])
                        out_depth[yy, xx] = ad[p]
                        out_T[yy, xx] = abs(T[p])
                        out_last[yy, xx] = np.int32(min(n_list, act[p]))
            k += 1
        out_n[w] = n_pairs


@njit(parallel=True, fastmath=_FM, cache=True)
def _backward(rec, offsets, ids, tiles, n_workers, tile_size, tiles_x, width, height, T_final, n_last, g_rgb,
              g_alpha, g_depth, out_grad, counter):  # pragma: no cover - numba
    """Back-to-front pass; writes d loss / d (2D Gaussian parameters) per intersection into out_grad
    (rows of intersections that touch no pixel are left as they are: zero).

    Each row run takes two pixel loops: the first updates the pixels' state and keeps three values per
    pixel, the second sums the ten gradient terms. In one loop the ten sums and the state did not fit
    the 16 vector registers and were spilled every iteration (one loop was ~25 % slower at 960x540)."""
    ts = tile_size
    npix = ts * ts
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        work = _scratch(13)
        px = _field(work, 0, npix)
        py = _field(work, 1, npix)
        _local_pixels(px, py, ts)
        T = _field(work, 2, npix)
        Q = _field(work, 3, npix)  # sum over later Gaussians of q_j w_j
        gat = _field(work, 4, npix)  # dL/dalpha * T_final
        gr = _field(work, 5, npix)
        gg = _field(work, 6, npix)
        gb = _field(work, 7, npix)
        gd = _field(work, 8, npix)
        lastp = _field(work, 9, npix)
        # per pixel of the current Gaussian: weight, dL/dsigma and e dL/dalpha (for the second loop)
        sW = _field(work, 10, npix)
        sD = _field(work, 11, npix)
        sE = _field(work, 12, npix)
        buf = np.empty((_CH, _NREC), np.float32)
        flat = rec.reshape(-1)  # for _prefetch
        k = 0
        k_end = 0
        while True:
            if k >= k_end:  # next run of tiles
                k = _fetch_add(counter, 0, _RUN)
                if k >= n_sched:
                    break
                k_end = min(k + _RUN, n_sched)
            t = tiles[k]
            x_0, y_0, nx, ny = _tile_origin(t, tiles_x, ts, width, height)
            start = offsets[t]
            if nx < ts or ny < ts:  # pixels outside the image take no part
                T[:] = _ONE
                lastp[:] = _ZERO
                gat[:] = _ZERO
                gr[:] = _ZERO
                gg[:] = _ZERO
                gb[:] = _ZERO
                gd[:] = _ZERO
            Q[:] = _ZERO
            max_last = 0
            for cbk in range(ts // _LANES):
                for row in range(ny):
                    for lane in range(min(_LANES, nx - cbk * _LANES)):
                        p = (cbk * ts + row) * _LANES + lane
                        yy = y_0 + row
                        xx = x_0 + cbk * _LANES + lane
                        T[p] = T_final[yy, xx]
                        lastp[p] = _F32(n_last[yy, xx])
                        gat[p] = g_alpha[yy, xx] * T_final[yy, xx]
                        gr[p] = g_rgb[yy, xx, 0]
                        gg[p] = g_rgb[yy, xx, 1]
                        gb[p] = g_rgb[yy, xx, 2]
                        gd[p] = g_depth[yy, xx]
                        max_last = max(max_last, n_last[yy, xx])
            jhi = start + max_last
            while jhi > start:
                m = min(_CH, jhi - start)
                jlo = jhi - m
                _gather(rec, ids, jlo, m, buf)
                for jj in range(max(start, jlo - _CH), jlo):  # the next (earlier) chunk
                    _prefetch(flat, np.int64(ids[jj]) * _NREC)
                for i in range(m - 1, -1, -1):
                    j = jlo + i
                    mx, my, r0, r1, c0, c1, ha, cb, hc, o, cr, cg, cbl, z = _unpack(buf, i, x_0, y_0, ts)
                    if r1 <= r0 or c1 <= c0:
                        continue
                    jl = _F32(j - start)
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
                        b0, b1 = _block_rows(mx, my, blk, buf[i, 12], buf[i, 13], buf[i, 14], buf[i, 15], r0, r1, ts)
                        if b1 <= b0:
                            continue
                        ulo = np.uint64((blk * ts + b0) * _LANES)
                        for qq in range((b1 - b0) * _LANES):
                            p = ulo + np.uint64(qq)
                            dx = mx - px[p]
                            dy = my - py[p]
                            sig = ha * dx * dx + hc * dy * dy + cb * dx * dy  # as in the forward kernels
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
                            sW[p] = wt
                            sD[p] = -v * dlda  # d loss / d sigma
                            sE[p] = e * dlda
                            Q[p] += q * wt
                            T[p] = Tp * (inv if ok else _ONE)
                        for qq in range((b1 - b0) * _LANES):
                            p = ulo + np.uint64(qq)
                            dx = mx - px[p]
                            dy = my - py[p]
                            wt = sW[p]
                            dls = sD[p]
                            s_r += wt * gr[p]
                            s_g += wt * gg[p]
                            s_b += wt * gb[p]
                            s_z += wt * gd[p]
                            s_o += sE[p]
                            s_dx += dls * dx
                            s_dy += dls * dy
                            s_xx += dls * dx * dx
                            s_xy += dls * dx * dy
                            s_yy += dls * dy * dy
                    out_grad[j, 0] = _TWO * ha * s_dx + cb * s_dy
                    out_grad[j, 1] = cb * s_dx + _TWO * hc * s_dy
                    out_grad[j, 2] = _HALF * s_xx
                    out_grad[j, 3] = s_xy
                    out_grad[j, 4] = _HALF * s_yy
                    out_grad[j, 5] = s_o
                    out_grad[j, 6] = s_r
                    out_grad[j, 7] = s_g
                    out_grad[j, 8] = s_b
                    out_grad[j, 9] = s_z
                jhi = jlo
            k += 1


@njit(cache=True)
def _reduce(ids, grad_isect, n):  # pragma: no cover - numba
    """Sum per-intersection gradients [M, 10] into per-Gaussian gradients [n, 10] (in list order, so
    deterministic); the output rows are prefetched 32 intersections ahead, since the random
    read-modify-writes would otherwise wait on memory one after the other."""
    nc = grad_isect.shape[1]
    out = np.zeros((n, nc), np.float32)
    flat = out.reshape(-1)
    m = ids.shape[0]
    for j in range(m):
        if j + 32 < m:
            _prefetch(flat, np.int64(ids[j + 32]) * nc)
        g = ids[j]
        for c in range(nc):
            out[g, c] += grad_isect[j, c]
    return out


def _n_workers() -> int:
    """Parallel workers of the tile kernels: numba's thread count (``NUMBA_NUM_THREADS``), as every
    other numba kernel here. Not also capped by torch's: the trainer runs torch's own small ops on one
    thread (``TrainConfig.threads``), and that cap had given training's tile kernels a single worker
    (on 2 cores the training runs measured the same either way, within noise)."""
    return max(1, numba.get_num_threads())


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).numpy())


def _prepare(means2d, conics, colors, opacities, depths, radii, width, height, tile_size, first_background=None):
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    r2 = np.ascontiguousarray(radii.detach().to(torch.int32).numpy())  # [N, 2]
    z = _np32(depths)  # [N]
    rec = np.empty((r2.shape[0], _NREC), np.float32)  # [N, 16]
    if r2.shape[0]:
        _records(_np32(means2d), _np32(conics), _np32(colors), _np32(opacities), z, r2, rec)
    offsets, ids = _bin(rec, r2, z, tile_size, tiles_x, tiles_y)
    if first_background is not None and first_background < r2.shape[0]:
        offsets, ids = _trim_tails(offsets, ids, first_background)
    tiles = _tile_schedule(offsets)
    return (rec,), offsets, ids, tiles, tiles_x


def _render(arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, save: bool, count: bool = False):
    rgb = np.zeros((height, width, 3), np.float32)
    alpha = np.zeros((height, width), np.float32)
    dsum = np.zeros((height, width), np.float32)
    if not save:
        if tiles.size:
            _forward_render(*arrays, offsets, ids, tiles, _n_workers(), tile_size, tiles_x, width, height,
                            rgb, alpha, dsum, np.zeros(1, np.int64))
        return rgb, alpha, dsum, None, None
    T = np.ones((height, width), np.float32)
    last = np.zeros((height, width), np.int32)
    nw = _n_workers()
    n_pairs = np.zeros(nw, np.float64)
    if tiles.size:
        _forward_train(*arrays, offsets, ids, tiles, nw, tile_size, tiles_x, width, height,
                       rgb, alpha, dsum, T, last, n_pairs, np.zeros(1, np.int64))
    if count:  # the number of Gaussian-pixel pairs composited
        return rgb, alpha, dsum, T, last, int(n_pairs.sum())
    return rgb, alpha, dsum, T, last


class _CompositeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, radii, width, height, tile_size, first_bg):
        arrays, offsets, ids, tiles, tiles_x = _prepare(
            means2d, conics, colors, opacities, depths, radii, width, height, tile_size, first_bg
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
                      _np32(g_rgb), _np32(g_alpha[..., 0]), _np32(g_depth[..., 0]), grad_isect, np.zeros(1, np.int64))
        g = torch.from_numpy(_reduce(ids, grad_isect, n))  # [N, 10]
        dt = g_rgb.dtype
        return (g[:, 0:2].to(dt), g[:, 2:5].to(dt), g[:, 6:9].to(dt), g[:, 5].to(dt), g[:, 9].to(dt),
                None, None, None, None, None)


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
    first_background: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite projected Gaussians with the numba kernels: colour [H, W, 3], alpha [H, W, 1], sum z*w [H, W, 1].

    Same rules and outputs as :func:`plantsplat.raster.reference.composite_reference`; differentiable
    with respect to means2d, conics, colors, opacities and depths. Gaussians from index
    ``first_background`` on are dropped from the end of each tile's list (see ``trailing_background``
    in :func:`plantsplat.raster.rasterize`).

    Example:
        >>> c, a, d = composite_cpu(torch.tensor([[4.0, 4.0]]), torch.tensor([[1.0, 0.0, 1.0]]),
        ...     torch.ones(1, 3), torch.tensor([0.5]), torch.tensor([2.0]), torch.tensor([[3, 3]]), 8, 8)
        >>> round(float(a[3, 3, 0]), 4)  # 0.5 * exp(-0.5 * (0.5^2 + 0.5^2)) at pixel centre (3.5, 3.5)
        0.3894
    """
    if tile_size % _LANES or tile_size > _TS_MAX:
        raise RasterInputError(
            f"rasterize: the cpu backend needs tile_size to be a multiple of {_LANES} up to {_TS_MAX}, got {tile_size}"
        )
    inputs = (means2d, conics, colors, opacities, depths)
    if torch.is_grad_enabled() and any(t.requires_grad for t in inputs):
        return _CompositeCPU.apply(means2d, conics, colors, opacities, depths, radii, width, height, tile_size,
                                   first_background)
    arrays, offsets, ids, tiles, tiles_x = _prepare(
        means2d, conics, colors, opacities, depths, radii, width, height, tile_size, first_background
    )
    rgb, alpha, dsum, _, _ = _render(arrays, offsets, ids, tiles, tiles_x, width, height, tile_size, False)
    dt = means2d.dtype
    return (torch.from_numpy(rgb).to(dt), torch.from_numpy(alpha)[..., None].to(dt),
            torch.from_numpy(dsum)[..., None].to(dt))

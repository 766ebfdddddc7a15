"""CPU backend: tile-parallel numba kernels for compositing, with a hand-written backward pass.

Projection and SH colours are vectorised PyTorch (:mod:`plantsplat.raster.projection`, autograd
differentiates them); this module composites the projected 2D Gaussians, which is where almost all
the time goes. The steps, all in float32:

1. ``_bin``: tile boxes from the screen radii (as gsplat), visible Gaussians sorted by depth once,
   then a stable counting sort into per-tile lists, so each tile's list is front to back.
2. ``_forward``: parallel over workers, each taking every ``n_workers``-th non-empty tile from a
   list sorted by work (empty tiles are skipped entirely); within a tile, one Gaussian at a time in
   depth order, vectorised over the tile's pixels; the tile stops once every pixel's transmittance
   has reached the stop threshold. Saves per pixel the final transmittance and the number of
   Gaussians processed, for the backward pass.
3. ``_backward``: the same tiles back to front, recovering each Gaussian's transmittance by division;
   gradients are written per (tile, Gaussian) intersection (no atomics, no races, deterministic)
   and summed per Gaussian afterwards (``_reduce``).

Under ``torch.no_grad()`` (or when no input needs a gradient) only ``_bin`` and ``_forward`` run and
nothing is kept.
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
_LANES = 8  # tile_size must be a multiple of this (so tile_size^2 is a multiple of _BLOCK)
_BLOCK = 16  # pixel loops run over multiples of this many pixels (vector width x unroll)
_SIG_MAX = _F32(6.0)  # exp(-6) < 1/255: larger sigma can never give a visible alpha
_LOG2E = _F32(1.4426950408889634)
_LN2_HI = _F32(0.693145751953125)
_LN2_LO = _F32(1.428606765330187e-06)
_EIGHT = _F32(8.0)
_FOUR = _F32(4.0)
_TWO = _F32(2.0)


@njit(inline="always", fastmath=_FM, cache=True)
def _exp_neg(s):  # pragma: no cover - numba
    """exp(-s) for s clamped to [0, 6], in float32 arithmetic the compiler can vectorise.

    libm's expf is a scalar call that stops the pixel loop from vectorising, so this is the usual
    range reduction exp(-s) = 2^-n exp(n ln2 - s) with a degree-6 polynomial on [-0.35, 0.35] and
    2^-n (n <= 9) from selects. Max relative error 2.5e-7 on [0, 6] (float32 expf: 2.0e-7).
    """
    s = min(max(s, _ZERO), _SIG_MAX)
    n = np.float32(np.int32(s * _LOG2E + _HALF))  # round(s / ln2); int32 keeps it vectorisable
    r = (n * _LN2_HI - s) + n * _LN2_LO
    p = _F32(1.0 / 720.0)
    p = p * r + _F32(1.0 / 120.0)
    p = p * r + _F32(1.0 / 24.0)
    p = p * r + _F32(1.0 / 6.0)
    p = p * r + _HALF
    p = p * r + _ONE
    p = p * r + _ONE
    p = p * (_F32(1.0 / 256.0) if n >= _EIGHT else _ONE)
    n = n - (_EIGHT if n >= _EIGHT else _ZERO)
    p = p * (_F32(1.0 / 16.0) if n >= _FOUR else _ONE)
    n = n - (_FOUR if n >= _FOUR else _ZERO)
    p = p * (_F32(0.25) if n >= _TWO else _ONE)
    n = n - (_TWO if n >= _TWO else _ZERO)
    return p * (_HALF if n >= _ONE else _ONE)


@njit(inline="always", cache=True)
def _span(m, r, origin, ts):  # pragma: no cover - numba
    """Tile-local pixel range [lo, hi) whose centres lie within r + 0.05 of m along one axis.

    Beyond the screen radius r (>= extent * sqrt(cov_ii), with extent = sqrt(2 ln(255 opacity)))
    the Mahalanobis distance alone makes alpha < 1/255, so those pixels can be skipped exactly.
    """
    lo = min(max(math.ceil(m - _F32(r) - _F32(0.55)) - origin, 0.0), ts)
    hi = min(max(math.floor(m + _F32(r) - _F32(0.45)) - origin + 1.0, 0.0), ts)
    return int(lo), int(hi)


@njit(cache=True)
def _bin(means2d, radii, depths, tile_size, tiles_x, tiles_y):  # pragma: no cover - numba
    """Per-tile depth-sorted Gaussian lists: (offsets [n_tiles + 1] int64, ids [n_isects] int32)."""
    n = means2d.shape[0]
    n_tiles = tiles_x * tiles_y
    ts = _F32(tile_size)
    box = np.zeros((n, 4), np.int64)
    n_vis = 0
    for g in range(n):
        if radii[g, 0] <= 0 or radii[g, 1] <= 0:
            continue
        mx = means2d[g, 0] / ts
        my = means2d[g, 1] / ts
        rx = _F32(radii[g, 0]) / ts
        ry = _F32(radii[g, 1]) / ts
        x0 = min(max(math.floor(mx - rx), 0.0), tiles_x)
        y0 = min(max(math.floor(my - ry), 0.0), tiles_y)
        x1 = min(max(math.ceil(mx + rx), 0.0), tiles_x)
        y1 = min(max(math.ceil(my + ry), 0.0), tiles_y)
        box[g, 0] = int(x0)
        box[g, 1] = int(y0)
        box[g, 2] = int(x1)
        box[g, 3] = int(y1)
        if x1 > x0 and y1 > y0:
            n_vis += 1
    vis = np.empty(n_vis, np.int64)
    k = 0
    for g in range(n):
        if radii[g, 0] > 0 and radii[g, 1] > 0 and box[g, 2] > box[g, 0] and box[g, 3] > box[g, 1]:
            vis[k] = g
            k += 1
    order = vis[np.argsort(depths[vis], kind="mergesort")]  # stable: ties keep index order
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
            for tx in range(box[g, 0], box[g, 2]):
                t = ty * tiles_x + tx
                ids[cursor[t]] = g
                cursor[t] += 1
    return offsets, ids


def _tile_schedule(offsets: np.ndarray) -> np.ndarray:
    """Non-empty tiles, most intersections first (workers take them round-robin)."""
    counts = np.diff(offsets)  # [n_tiles]
    nonempty = np.flatnonzero(counts)
    return nonempty[np.argsort(-counts[nonempty], kind="stable")].astype(np.int64)


@njit(parallel=True, fastmath=_FM, cache=True)
def _forward(means2d, conics, colors, opac, depths, radii, offsets, ids, tiles, n_workers, tile_size, tiles_x,
             width, height, out_rgb, out_alpha, out_depth, out_T, out_last, out_n):  # pragma: no cover - numba
    """Composite every listed tile: colour, alpha, sum z*w; if out_T.size, final T and list position of
    the last composited Gaussian; if out_n.size, the number of Gaussians composited per pixel."""
    ts = tile_size
    npix = ts * ts
    save = out_T.shape[0] > 0
    count = out_n.shape[0] > 0
    n_sched = tiles.shape[0]
    for w in prange(n_workers):
        px = np.empty(npix, np.float32)
        py = np.empty(npix, np.float32)
        T = np.empty(npix, np.float32)
        ar = np.empty(npix, np.float32)
        ag = np.empty(npix, np.float32)
        ab = np.empty(npix, np.float32)
        ad = np.empty(npix, np.float32)
        act = np.empty(npix, np.float32)  # 1 while the pixel is still compositing, else 0
        last = np.empty(npix, np.float32)  # list position (1-based) of the last composited Gaussian
        ncon = np.empty(npix, np.float32)
        for k in range(w, n_sched, n_workers):
            t = tiles[k]
            tyi = t // tiles_x
            txi = t - tyi * tiles_x
            x_0 = txi * ts
            y_0 = tyi * ts
            start = offsets[t]
            end = offsets[t + 1]
            n_act = 0
            for p in range(npix):
                iy = p // ts
                ix = p - iy * ts
                px[p] = _F32(x_0 + ix) + _HALF
                py[p] = _F32(y_0 + iy) + _HALF
                T[p] = _ONE
                ar[p] = _ZERO
                ag[p] = _ZERO
                ab[p] = _ZERO
                ad[p] = _ZERO
                last[p] = _ZERO
                ncon[p] = _ZERO
                inside = (x_0 + ix < width) and (y_0 + iy < height)
                act[p] = _ONE if inside else _ZERO
                n_act += 1 if inside else 0
            for j in range(start, end):
                if n_act == 0:
                    break
                g = ids[j]
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
                jl = _F32(j - start + 1)
                r0, r1 = _span(my, radii[g, 1], y_0, ts)
                lo = (r0 * ts) // _BLOCK * _BLOCK
                hi = min(npix, (r1 * ts + _BLOCK - 1) // _BLOCK * _BLOCK) if r1 > r0 else lo
                ulo = np.uint64(lo)
                n_stop = _ZERO  # float32 counter keeps the loop in 8-wide float vectors
                # whole rows r0..r1 (rounded out to _BLOCK pixels so the vector loop has no scalar
                # tail); unsigned indices: numba's negative-index wraparound stops vectorisation
                for q in range(hi - lo):
                    p = ulo + np.uint64(q)
                    dx = mx - px[p]
                    dy = my - py[p]
                    sig = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
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
                    last[p] = max(last[p], jl if use else _ZERO)
                    ncon[p] += _ONE if use else _ZERO
                    act[p] = act[p] * (_ZERO if stop else _ONE)
                    n_stop += _ONE if stop else _ZERO
                n_act -= int(n_stop)
            for p in range(npix):
                iy = p // ts
                ix = p - iy * ts
                yy = y_0 + iy
                xx = x_0 + ix
                if xx < width and yy < height:
                    out_rgb[yy, xx, 0] = ar[p]
                    out_rgb[yy, xx, 1] = ag[p]
                    out_rgb[yy, xx, 2] = ab[p]
                    out_alpha[yy, xx] = _ONE - T[p]
                    out_depth[yy, xx] = ad[p]
                    if save:
                        out_T[yy, xx] = T[p]
                        out_last[yy, xx] = np.int32(last[p])
                    if count:
                        out_n[yy, xx] = np.int32(ncon[p])


@njit(parallel=True, fastmath=_FM, cache=True)
def _backward(means2d, conics, colors, opac, depths, radii, offsets, ids, tiles, n_workers, tile_size, tiles_x,
              width, height, T_final, n_last, g_rgb, g_alpha, g_depth, out_grad):  # pragma: no cover
    """Back-to-front pass; writes d loss / d (2D Gaussian parameters) per intersection into out_grad."""
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
            txi = t - tyi * tiles_x
            x_0 = txi * ts
            y_0 = tyi * ts
            start = offsets[t]
            max_last = 0
            for p in range(npix):
                iy = p // ts
                ix = p - iy * ts
                xx = x_0 + ix
                yy = y_0 + iy
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
                jl = _F32(jl64)
                g = ids[j]
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
                s_mx = _ZERO
                s_my = _ZERO
                s_ca = _ZERO
                s_cb = _ZERO
                s_cc = _ZERO
                s_o = _ZERO
                s_r = _ZERO
                s_g = _ZERO
                s_b = _ZERO
                s_z = _ZERO
                r0, r1 = _span(my, radii[g, 1], y_0, ts)
                lo = (r0 * ts) // _BLOCK * _BLOCK
                hi = min(npix, (r1 * ts + _BLOCK - 1) // _BLOCK * _BLOCK) if r1 > r0 else lo
                ulo = np.uint64(lo)
                # whole rows r0..r1 (rounded out to _BLOCK pixels so the vector loop has no scalar
                # tail); unsigned indices: numba's negative-index wraparound stops vectorisation
                for q in range(hi - lo):
                    p = ulo + np.uint64(q)
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
                    s_mx += dls * (ca * dx + cb * dy)
                    s_my += dls * (cb * dx + cc * dy)
                    s_ca += dls * _HALF * dx * dx
                    s_cb += dls * dx * dy
                    s_cc += dls * _HALF * dy * dy
                    Q[p] += q * wt
                    T[p] = Tp * (inv if ok else _ONE)
                out_grad[j, 0] = s_mx
                out_grad[j, 1] = s_my
                out_grad[j, 2] = s_ca
                out_grad[j, 3] = s_cb
                out_grad[j, 4] = s_cc
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
    if save:
        T = np.ones((height, width), np.float32)
        last = np.zeros((height, width), np.int32)
    else:
        T = np.empty((0, 0), np.float32)
        last = np.empty((0, 0), np.int32)
    n_con = np.zeros((height, width) if count else (0, 0), np.int32)
    if tiles.size:
        _forward(*arrays, offsets, ids, tiles, _n_workers(), tile_size, tiles_x, width, height,
                 rgb, alpha, dsum, T, last, n_con)
    if count:
        return rgb, alpha, dsum, T, last, n_con
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

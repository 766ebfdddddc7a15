"""Fused SSIM and training loss for the CPU: numba kernels for the value and a hand-written gradient.

The training loss ``(1 - l) L1 + l (1 - SSIM)`` needs SSIM of the render against the ground truth
at every step. As separable depthwise ``conv2d`` calls in PyTorch (11x11 Gaussian window, sigma
1.5, zero padding, the usual ``C1 = 0.01^2``, ``C2 = 0.03^2``) it costs more than rasterizing the
image on a CPU. Here, row by row of the interleaved ``[H, W, 3]`` image, the five local moments
(``x, y, x^2, y^2, x y``) are blurred vertically straight from the 11 input rows around the output
row (they stay in cache from one row to the next), then horizontally, then go into the SSIM
formula: no planar copies and no full-image moment maps. Each 1-D blur evaluates the whole
symmetric 11-tap window per output element in registers (horizontally the taps are 3 floats apart,
a compile-time constant, so the loop over the row vectorises); the previous version, which added
one tap at a time into buffers of whole rows, was about 2x slower, bound by loads and stores. The
forward pass also stores ``dS/dmu_x``, ``dS/dE[x^2]`` and ``dS/dE[x y]`` per pixel, and the
backward pass blurs those three maps with the same (symmetric) window:

    dSSIM/dx = (G * dS/dmu_x + 2 x G * dS/dE[x^2] + y G * dS/dE[x y]) / (C H W)

:func:`photometric_loss_cpu` fuses the rest of a training step's loss into the same passes: the
render is composited over the background in a first pass over the rows (``x = colour + (1 - alpha)
B``), which also sums L1 and the squared error; its backward pass gives the gradients of the
colour and the alpha directly. That replaces about ten full-image PyTorch operations per step
(about a fifth of a step at 896 px).

Same values as :func:`plantsplat.train.metrics.ssim` without a mask (tested against the PyTorch
version, values and gradients). Only the prediction gets a gradient.

Example:
    >>> import torch
    >>> x = torch.rand(20, 24, 3)
    >>> round(float(ssim_cpu(x, x)), 5)
    1.0
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from plantsplat.raster.numba_config import FASTMATH  # (also numba's threading layer)

_F32 = np.float32
_FM = set(FASTMATH)
_R = 5  # window radius (11 taps)
_C = 3  # channels of the interleaved rows: horizontal taps are _C floats apart
_C1 = _F32(0.01**2)
_C2 = _F32(0.03**2)


def _window(sigma: float = 1.5) -> np.ndarray:
    g = np.exp(-((np.arange(2 * _R + 1, dtype=np.float64) - _R) ** 2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


_TAPS = _window()[: _R + 1].copy()
"""The six distinct taps of the symmetric 11-tap window, as the kernels take it."""
_BLOCK = 32  # output rows per parallel task


@njit(inline="always")
def _rows11(a, i, zero, c0, c1):  # pragma: no cover - numba
    """Columns c0..c1 of rows i - 5 .. i + 5 of a (the zero row where outside the image: zero padding).

    Slices, so that the loops over them start at 0: numba wraps negative indices, and LLVM vectorises a loop
    only where it can tell the index is not negative (loops from a computed start made the passes 6-9x slower)."""
    h = a.shape[0]
    z = zero[: c1 - c0]
    return (a[i - 5, c0:c1] if i >= 5 else z, a[i - 4, c0:c1] if i >= 4 else z, a[i - 3, c0:c1] if i >= 3 else z,
            a[i - 2, c0:c1] if i >= 2 else z, a[i - 1, c0:c1] if i >= 1 else z, a[i, c0:c1],
            a[i + 1, c0:c1] if i + 1 < h else z, a[i + 2, c0:c1] if i + 2 < h else z,
            a[i + 3, c0:c1] if i + 3 < h else z, a[i + 4, c0:c1] if i + 4 < h else z,
            a[i + 5, c0:c1] if i + 5 < h else z)


@njit(inline="always", fastmath=_FM)
def _sym(g, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10):  # pragma: no cover - numba
    """sum_t g[t] v_t for the symmetric window (g[t] = g[10 - t])."""
    return (g[0] * (v0 + v10) + g[1] * (v1 + v9) + g[2] * (v2 + v8) + g[3] * (v3 + v7) + g[4] * (v4 + v6)
            + g[5] * v5)


@njit(inline="always", fastmath=_FM)
def _vblur(r, q, g):  # pragma: no cover - numba
    """Vertical blur at column q of the 11 rows r (from :func:`_rows11`)."""
    return _sym(g, r[0][q], r[1][q], r[2][q], r[3][q], r[4][q], r[5][q], r[6][q], r[7][q], r[8][q], r[9][q],
                r[10][q])


@njit(inline="always", fastmath=_FM)
def _hblur(p, o, g):  # pragma: no cover - numba
    """o[q] = sum_t g[t] p[q + t _C]: the horizontal blur of the zero-padded interleaved row p."""
    for q in range(o.shape[0]):
        o[q] = _sym(g, p[q], p[q + _C], p[q + 2 * _C], p[q + 3 * _C], p[q + 4 * _C], p[q + 5 * _C],
                    p[q + 6 * _C], p[q + 7 * _C], p[q + 8 * _C], p[q + 9 * _C], p[q + 10 * _C])


@njit(inline="always")
def _row_scratch(n):  # pragma: no cover - numba
    """A worker's buffers for rows of ``n`` floats: a zero row (above and below the image), the five vertically
    blurred moments with ``_R`` pixels of zeros on each side (zero padding), and the five blurred horizontally."""
    return np.zeros(n, np.float32), np.zeros((5, n + 2 * _R * _C), np.float32), np.empty((5, n), np.float32)


@njit(inline="always", fastmath=_FM)
def _vblur5(xs, ys, g, p0, p1, p2, p3, p4):  # pragma: no cover - numba
    """The five local moments (x, y, x^2, y^2, x y) of the 11 rows ``xs`` and ``ys`` (from :func:`_rows11`) blurred
    vertically, column by column, into p0..p4 (as long as the rows)."""
    for q in range(p0.shape[0]):
        a0, a1, a2, a3, a4, a5 = xs[0][q], xs[1][q], xs[2][q], xs[3][q], xs[4][q], xs[5][q]
        a6, a7, a8, a9, a10 = xs[6][q], xs[7][q], xs[8][q], xs[9][q], xs[10][q]
        v0, v1, v2, v3, v4, v5 = ys[0][q], ys[1][q], ys[2][q], ys[3][q], ys[4][q], ys[5][q]
        v6, v7, v8, v9, v10 = ys[6][q], ys[7][q], ys[8][q], ys[9][q], ys[10][q]
        p0[q] = _sym(g, a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10)
        p1[q] = _sym(g, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10)
        p2[q] = _sym(g, a0 * a0, a1 * a1, a2 * a2, a3 * a3, a4 * a4, a5 * a5, a6 * a6, a7 * a7, a8 * a8, a9 * a9,
                     a10 * a10)
        p3[q] = _sym(g, v0 * v0, v1 * v1, v2 * v2, v3 * v3, v4 * v4, v5 * v5, v6 * v6, v7 * v7, v8 * v8, v9 * v9,
                     v10 * v10)
        p4[q] = _sym(g, a0 * v0, a1 * v1, a2 * v2, a3 * v3, a4 * v4, a5 * v5, a6 * v6, a7 * v7, a8 * v8, a9 * v9,
                     a10 * v10)


@njit(parallel=True, fastmath=_FM, cache=True, error_model="numpy")
def _map(x, y, g, out):  # pragma: no cover - numba
    """The SSIM map of x against y (interleaved [H, W*3]) into out: the moments blurred vertically from the 11 rows
    around each output row, then horizontally (as :func:`_fwd`, over every window)."""
    h, n = y.shape
    nblk = (h + _BLOCK - 1) // _BLOCK
    for b in prange(nblk):
        zero, pad, mu = _row_scratch(n)
        for i in range(b * _BLOCK, min(h, (b + 1) * _BLOCK)):
            xs = _rows11(x, i, zero, 0, n)
            ys = _rows11(y, i, zero, 0, n)
            o0 = _R * _C
            _vblur5(xs, ys, g, pad[0, o0:o0 + n], pad[1, o0:o0 + n], pad[2, o0:o0 + n], pad[3, o0:o0 + n],
                    pad[4, o0:o0 + n])
            for m in range(5):
                _hblur(pad[m], mu[m], g)
            o = out[i]
            for q in range(n):
                _, _, c1, c2, d1, d2 = _terms(mu[0], mu[1], mu[2], mu[3], mu[4], q)
                o[q] = (c1 * c2) / (d1 * d2)


@njit(inline="always")
def _reach(rng, i, k, w):  # pragma: no cover - numba
    """The pixel range within ``k`` px of the ranges ``rng[r]`` (``[a, b)`` per row, ``(0, 0)`` for none) of rows
    i - k .. i + k, within ``[0, w)``; ``(0, 0)`` if they are all empty."""
    h = rng.shape[0]
    lo = w
    hi = 0
    for r in range(max(0, i - k), min(h, i + k + 1)):
        if rng[r, 1] > rng[r, 0]:
            lo = min(lo, rng[r, 0])
            hi = max(hi, rng[r, 1])
    if hi <= lo:
        return 0, 0
    return max(0, lo - k), min(w, hi + k)


@njit(inline="always", fastmath=_FM)
def _terms(m0, m1, m2, m3, m4, q):  # pragma: no cover - numba
    """mu_x, mu_y and the four factors of SSIM = (a1 a2) / (b1 b2) at column q of the blurred moments m0..m4
    (x, y, x^2, y^2, x y)."""
    mx = m0[q]
    my = m1[q]
    a1 = _F32(2.0) * mx * my + _C1
    a2 = _F32(2.0) * (m4[q] - mx * my) + _C2
    b1 = mx * mx + my * my + _C1
    b2 = m2[q] + m3[q] - mx * mx - my * my + _C2
    return mx, my, a1, a2, b1, b2


@njit(inline="always", fastmath=_FM)
def _ssim_row(m0, m1, m2, m3, m4):  # pragma: no cover - numba
    """Sum of the SSIM map over (part of) one row from its blurred moments m0..m4."""
    s_row = _F32(0.0)
    for q in range(m0.shape[0]):
        _, _, a1, a2, b1, b2 = _terms(m0, m1, m2, m3, m4, q)
        s_row += (a1 * a2) / (b1 * b2)
    return s_row


@njit(inline="always", fastmath=_FM)
def _ssim_row_grad(m0, m1, m2, m3, m4, d0, d1, d2):  # pragma: no cover - numba
    """As :func:`_ssim_row`, also writing dS/dmu_x, dS/dE[x^2], dS/dE[x y] into d0, d1, d2."""
    s_row = _F32(0.0)
    for q in range(m0.shape[0]):
        mx, my, a1, a2, b1, b2 = _terms(m0, m1, m2, m3, m4, q)
        ib1 = _F32(1.0) / b1  # b1 >= C1, b2 >= C2 (up to rounding): never zero
        ib2 = _F32(1.0) / b2
        ib = ib1 * ib2
        s = a1 * a2 * ib
        s_row += s
        # no division by a1 or a2: a2 = 2 cov(x, y) + C2 is exactly zero where a negative covariance cancels C2,
        # and the former s / a2 was then 0 * inf = NaN in the gradient of a finite loss
        d0[q] = _F32(2.0) * (my * (a2 - a1) * ib + mx * s * (ib2 - ib1))
        d1[q] = -s * ib2
        d2[q] = _F32(2.0) * a1 * ib
    return s_row


_FWD_SIGNATURE = ("void(f4[:, ::1], f4[:, ::1], f4[::1], f4[:, ::1], f4[::1], b1, f4[:, ::1], f4[:, :, ::1], f4[:, ::1], "
                  "f4[:, :], f4[:, :], i8[:, ::1], i8[:, ::1])")
""":func:`_fwd`'s one signature. ``img`` and ``img_alpha`` are crops of whole frames (strided rows) or, as a whole frame
or ``_NO_ALPHA``, contiguous: typed for any layout, so that both take the same machine code. Left to numba, each
layout compiled a specialisation of its own, 14 s each on the 2-core machine (the quick model's whole frames, then
the object model's crops; a crop as wide as the frame would have compiled a third in the middle of a training)."""


@njit(_FWD_SIGNATURE, parallel=True, fastmath=_FM, cache=True, error_model="numpy")
def _fwd(col, alpha, bg, y, g, want_grad, x, dmaps, sums, img, img_alpha, live, rng):  # pragma: no cover - numba
    """SSIM of x = col + (1 - alpha) bg (written to x) against y, interleaved [H, W*3] (alpha
    [H, W], g the window's six distinct taps): sums[i] = (row i's SSIM sum, |x - y| sum,
    (x - y)^2 sum); if want_grad, dmaps[0..2, i] = dS/dmu_x, dS/dE[x^2], dS/dE[x y] per pixel and
    channel. When img_alpha has rows, y is written first: y = img img_alpha + (1 - img_alpha) bg
    (img [H, W*3] and img_alpha [H, W] may be views with strided rows, a crop of a whole frame).

    Per output row: the five local moments are blurred vertically from the 11 input rows around it
    (which stay in cache from one row to the next), then horizontally, then go straight into the
    SSIM formula, so no moment maps are written.

    Only the windows holding a pixel where x != y are computed: ``live[i]`` gets the pixel range ``[a, b)``
    from the first to the last such pixel of row i (``(0, 0)`` if none) and ``rng[i]`` the pixel range of
    output windows of row i that hold one. Where x == y over a whole window, SSIM is exactly 1 and the window adds nothing
    to any gradient (its dS/dmu_x is 0, and 2 x dS/dE[x^2] + y dS/dE[x y] = 2 (y - x) / b2 = 0 at each of
    its pixels): those windows count 1 each and get zero derivative maps. Object mode's crops are
    mostly such windows, background over background."""
    h, n = y.shape
    for row in prange(h):
        xr = x[row]
        cr = col[row]
        ar = alpha[row]
        yr = y[row]
        for p in range(ar.shape[0]):
            t = _F32(1.0) - ar[p]
            for c in range(_C):
                xr[p * _C + c] = cr[p * _C + c] + t * bg[c]
        if img_alpha.shape[0] > 0:
            ir = img[row]
            gr = img_alpha[row]
            for p in range(gr.shape[0]):
                a = gr[p]
                t = _F32(1.0) - a
                for c in range(_C):
                    yr[p * _C + c] = ir[p * _C + c] * a + t * bg[c]
        s_abs = _F32(0.0)
        s_sq = _F32(0.0)
        for q in range(n):
            d = xr[q] - yr[q]
            s_abs += abs(d)
            s_sq += d * d
        sums[row, 1] = s_abs
        sums[row, 2] = s_sq
        # the first and last pixel where x != y (scans that stop there: the loop above stays vectorised)
        first = n
        for q in range(n):
            if xr[q] != yr[q]:
                first = q
                break
        last = -1
        for q in range(n - 1, first - 1, -1):
            if xr[q] != yr[q]:
                last = q
                break
        live[row, 0] = first // _C if last >= 0 else 0
        live[row, 1] = last // _C + 1 if last >= 0 else 0
    w = n // _C
    for i in range(h):  # the windows (radius _R) that hold a live pixel of rows i - _R .. i + _R
        a, z = _reach(live, i, _R, w)
        rng[i, 0] = a
        rng[i, 1] = z
    nblk = (h + _BLOCK - 1) // _BLOCK
    for b in prange(nblk):
        zero, pad, mu = _row_scratch(n)
        for i in range(b * _BLOCK, min(h, (b + 1) * _BLOCK)):
            q0 = rng[i, 0] * _C
            q1 = rng[i, 1] * _C
            if want_grad:
                # zeros where :func:`_bwd` reads this row outside its own windows: within 2 window radii of the
                # windows computed in the rows within 2 window radii of it
                z0, z1 = _reach(rng, i, 2 * _R, w)
                for m in range(3):
                    dm = dmaps[m, i]
                    for q in range(z0 * _C, min(q0, z1 * _C)):
                        dm[q] = _F32(0.0)
                    for q in range(max(q1, z0 * _C), z1 * _C):
                        dm[q] = _F32(0.0)
            if q1 <= q0:
                sums[i, 0] = _F32(n)
                continue
            # the vertical blur where the windows of q0..q1 read it (pad's entries elsewhere are stale or zero)
            c0 = max(0, q0 - _R * _C)
            c1 = min(n, q1 + _R * _C)
            xs = _rows11(x, i, zero, c0, c1)
            ys = _rows11(y, i, zero, c0, c1)
            p0 = pad[0, _R * _C + c0:_R * _C + c1]
            p1 = pad[1, _R * _C + c0:_R * _C + c1]
            p2 = pad[2, _R * _C + c0:_R * _C + c1]
            p3 = pad[3, _R * _C + c0:_R * _C + c1]
            p4 = pad[4, _R * _C + c0:_R * _C + c1]
            _vblur5(xs, ys, g, p0, p1, p2, p3, p4)
            L = q1 - q0
            for m in range(5):
                _hblur(pad[m, q0:q1 + 2 * _R * _C], mu[m, :L], g)
            if want_grad:
                sums[i, 0] = _ssim_row_grad(mu[0, :L], mu[1, :L], mu[2, :L], mu[3, :L], mu[4, :L], dmaps[0, i, q0:q1],
                                            dmaps[1, i, q0:q1], dmaps[2, i, q0:q1]) + _F32(n - L)
            else:
                sums[i, 0] = _ssim_row(mu[0, :L], mu[1, :L], mu[2, :L], mu[3, :L], mu[4, :L]) + _F32(n - L)


@njit(parallel=True, fastmath=_FM, cache=True, error_model="numpy")
def _bwd(dmaps, x, y, bg, g, s_ssim, s_l1, dx, dalpha, rng):  # pragma: no cover - numba
    """dx = s_ssim (G * dmaps[0] + 2 x (G * dmaps[1]) + y (G * dmaps[2])) + s_l1 sign(x - y) and, when
    dalpha has rows, dalpha = -sum_c dx_c bg_c (x = col + (1 - alpha) bg). Blurred as :func:`_fwd`:
    vertically from the 11 rows around each output row, then horizontally. ``rng``: :func:`_fwd`'s ranges of
    the windows whose derivative maps are not zero; the blurred maps are computed only within reach of them."""
    h, n = y.shape
    w = n // _C
    want_alpha = dalpha.shape[0] > 0
    nblk = (h + _BLOCK - 1) // _BLOCK
    for b in prange(nblk):
        zero = np.zeros(n, np.float32)
        pad = np.zeros((3, n + 2 * _R * _C), np.float32)
        bd = np.empty((3, n), np.float32)
        for i in range(b * _BLOCK, min(h, (b + 1) * _BLOCK)):
            a, z = _reach(rng, i, _R, w)  # the pixels within a window radius of this row's nonzero maps
            q0 = a * _C
            q1 = z * _C
            if q1 > q0:
                c0 = max(0, q0 - _R * _C)
                c1 = min(n, q1 + _R * _C)
                for m in range(3):
                    rs = _rows11(dmaps[m], i, zero, c0, c1)
                    pm = pad[m, _R * _C + c0:_R * _C + c1]
                    for q in range(c1 - c0):
                        pm[q] = _vblur(rs, q, g)
                    _hblur(pad[m, q0:q1 + 2 * _R * _C], bd[m, q0:q1], g)
            xr = x[i]
            yr = y[i]
            o = dx[i]
            for q in range(n):
                d = xr[q] - yr[q]
                sg = _F32(1.0) if d > 0 else (_F32(-1.0) if d < 0 else _F32(0.0))
                o[q] = s_l1 * sg
            if q1 > q0:
                os_, xs_, ys_ = o[q0:q1], xr[q0:q1], yr[q0:q1]
                b0, b1, b2 = bd[0, q0:q1], bd[1, q0:q1], bd[2, q0:q1]
                for q in range(q1 - q0):
                    os_[q] += s_ssim * (b0[q] + _F32(2.0) * xs_[q] * b1[q] + ys_[q] * b2[q])
            if want_alpha:
                da = dalpha[i]
                for p in range(da.shape[0]):
                    acc = _F32(0.0)
                    for c in range(_C):
                        acc += o[p * _C + c] * bg[c]
                    da[p] = -acc


def _rows(t: Tensor) -> np.ndarray:
    """[H, W, C] tensor -> float32 [H, W*C] array (no copy when already contiguous float32)."""
    a = t.detach().to(torch.float32).contiguous().numpy()
    return a.reshape(a.shape[0], -1)


def _strided_rows(t: Tensor) -> np.ndarray:
    """[H, W, C] float32 tensor, possibly a crop of a larger image -> [H, W*C] array view (no copy when each row's
    W*C values are contiguous)."""
    a = t.detach()
    if a.dtype != torch.float32 or a.stride(-1) != 1 or (a.dim() == 3 and a.stride(-2) != a.shape[-1]):
        a = a.to(torch.float32).contiguous()
    a = a.numpy()
    return a.reshape(a.shape[0], -1)


def _run_fwd(col: Tensor, alpha: np.ndarray, bg: np.ndarray, gt: Tensor, want_grad: bool,
             gt_alpha: Tensor | None = None):
    c = _rows(col)
    if gt_alpha is None:
        y = _rows(gt)
        img, ga = _NO_ALPHA, _NO_ALPHA
    else:  # the target is composited over bg in the kernel's first pass, straight from the (cropped) frame
        img = _strided_rows(gt)
        ga = _strided_rows(gt_alpha)
        y = np.empty(img.shape, np.float32)
    h, n = y.shape
    x = np.empty_like(y)
    dmaps = np.empty((3, h, n) if want_grad else (3, 0, 0), np.float32)
    sums = np.zeros((h, 3), np.float32)
    live = np.empty((h, 2), np.int64)
    rng = np.empty((h, 2), np.int64)
    _fwd(c, alpha, bg, y, _TAPS, want_grad, x, dmaps, sums, img, ga, live, rng)
    tot = sums.astype(np.float64).sum(axis=0) / (h * n)  # mean SSIM, mean |x - y|, mean (x - y)^2
    return x, y, (dmaps, rng), tot


_NO_ALPHA = np.empty((0, 0), np.float32)


class _SSIMCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt):
        h, w = pred.shape[:2]
        want = bool(ctx.needs_input_grad[0])
        x, y, dmaps, tot = _run_fwd(pred, np.ones((h, w), np.float32), np.zeros(_C, np.float32), gt, want)
        if want:
            ctx.saved = (x, y, dmaps, pred.shape)
        return pred.new_tensor(float(tot[0]))

    @staticmethod
    def backward(ctx, g_out):
        x, y, (dmaps, rng), shape = ctx.saved
        h, n = x.shape
        out = np.empty_like(x)
        _bwd(dmaps, x, y, np.zeros(_C, np.float32), _TAPS, _F32(float(g_out) / (h * n)), _F32(0.0), out, _NO_ALPHA, rng)
        return torch.from_numpy(out).view(shape).to(g_out.dtype), None


class _LossCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, color, alpha, bg, gt, lam, gt_alpha):
        a = alpha.detach().to(torch.float32).contiguous().numpy().reshape(alpha.shape[0], alpha.shape[1])
        b = bg.detach().to(torch.float32).contiguous().numpy()
        want = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        x, y, dmaps, tot = _run_fwd(color, a, b, gt, want, gt_alpha)
        if want:
            ctx.saved = (x, b, y, dmaps, lam, color.shape, alpha.shape)
        mse = color.new_tensor(float(tot[2]))
        ctx.mark_non_differentiable(mse)
        return color.new_tensor(float((1.0 - lam) * tot[1] + lam * (1.0 - tot[0]))), mse

    @staticmethod
    def backward(ctx, g_loss, g_mse):
        x, b, y, (dmaps, rng), lam, cshape, ashape = ctx.saved
        h, n = y.shape
        gl = float(g_loss) / (h * n)
        dcol = np.empty_like(x)
        dalpha = np.empty((ashape[0], ashape[1]), np.float32) if ctx.needs_input_grad[1] else _NO_ALPHA
        _bwd(dmaps, x, y, b, _TAPS, _F32(-lam * gl), _F32((1.0 - lam) * gl), dcol, dalpha, rng)
        d_col = torch.from_numpy(dcol).view(cshape).to(g_loss.dtype)
        d_alpha = torch.from_numpy(dalpha).view(ashape).to(g_loss.dtype) if ctx.needs_input_grad[1] else None
        return d_col, d_alpha, None, None, None, None


def _check(pred: Tensor, gt: Tensor, name: str) -> None:
    if pred.shape != gt.shape or pred.dim() != 3 or pred.shape[2] != _C:
        raise ValueError(f"{name}: need two [H, W, 3] images of one shape, got {list(pred.shape)} and "
                         f"{list(gt.shape)}")
    if pred.shape[0] < 1 or pred.shape[1] < 1:
        raise ValueError(f"{name}: empty image")


def ssim_cpu(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean SSIM of two [H, W, 3] float images in [0, 1] (11x11 Gaussian window, sigma 1.5, zero
    padding); differentiable with respect to ``pred``. Computed in float32 with numba kernels.

    Example:
        >>> import torch
        >>> a = torch.zeros(16, 16, 3); b = torch.ones(16, 16, 3)
        >>> float(ssim_cpu(a, b)) < 0.01
        True
    """
    _check(pred, gt, "ssim_cpu")
    return _SSIMCPU.apply(pred, gt).to(pred.dtype)


def ssim_map_cpu(pred: Tensor, gt: Tensor) -> Tensor:
    """The per-pixel SSIM map ``[H, W, 3]`` of two [H, W, 3] float images in [0, 1] (11x11 Gaussian window, sigma
    1.5, zero padding), as :func:`plantsplat.train.metrics.ssim_map` computes it with PyTorch, in one numba pass over
    the rows (no gradient). For scoring renders: several times faster than the PyTorch convolutions on a CPU.

    Example:
        >>> import torch
        >>> x = torch.rand(20, 24, 3)
        >>> round(float(ssim_map_cpu(x, x).min()), 5)
        1.0
    """
    _check(pred, gt, "ssim_map_cpu")
    x, y = _rows(pred), _rows(gt)
    out = np.empty_like(x)
    _map(x, y, _TAPS, out)
    return torch.from_numpy(out).view(pred.shape).to(pred.dtype)


def photometric_loss_cpu(color: Tensor, alpha: Tensor, bg: Tensor, gt: Tensor,
                         ssim_lambda: float = 0.2, gt_alpha: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The 3DGS training loss of a render composited over a background, fused on the CPU.

    With ``x = color + (1 - alpha) bg`` (``color`` ``[H, W, 3]``, ``alpha`` ``[H, W, 1]``, ``bg``
    ``[3]``): ``loss = (1 - l) mean|x - gt| + l (1 - SSIM(x, gt))``, differentiable with respect to
    ``color`` and ``alpha``; also the mean squared error (for PSNR; no gradient). Equal to composing
    the PyTorch operations (tested, values and gradients). With ``gt_alpha`` ``[H, W, 1]`` the target is
    the frame ``gt`` composited over the same background, ``gt gt_alpha + (1 - gt_alpha) bg`` (object
    mode), computed in the kernel's first pass; ``gt`` and ``gt_alpha`` may then be crops (views) of
    whole frames, read without a copy.

    Example:
        >>> import torch
        >>> gt = torch.rand(12, 10, 3)
        >>> loss, mse = photometric_loss_cpu(gt.clone(), torch.ones(12, 10, 1), torch.zeros(3), gt)
        >>> round(float(loss), 5), float(mse)
        (0.0, 0.0)
    """
    _check(color, gt, "photometric_loss_cpu")
    if tuple(alpha.shape) != (color.shape[0], color.shape[1], 1) or tuple(bg.shape) != (_C,):
        raise ValueError(f"photometric_loss_cpu: need alpha [H, W, 1] and bg [3] for a {list(color.shape)} "
                         f"render, got {list(alpha.shape)} and {list(bg.shape)}")
    if gt_alpha is not None and tuple(gt_alpha.shape) != (color.shape[0], color.shape[1], 1):
        raise ValueError(f"photometric_loss_cpu: need gt_alpha [H, W, 1] for a {list(color.shape)} render, got "
                         f"{list(gt_alpha.shape)}")
    loss, mse = _LossCPU.apply(color, alpha, bg, gt, float(ssim_lambda), gt_alpha)
    return loss.to(color.dtype), mse


__all__ = ["photometric_loss_cpu", "ssim_cpu", "ssim_map_cpu"]

"""Fused SSIM loss for the CPU: numba kernels for the value and a hand-written gradient.

The training loss ``0.8 L1 + 0.2 (1 - SSIM)`` needs SSIM of the render against the ground truth at
every step. As separable depthwise ``conv2d`` calls in PyTorch (11x11 Gaussian window, sigma 1.5,
zero padding, the usual ``C1 = 0.01^2``, ``C2 = 0.03^2``) it costs more than rasterizing the image
on a CPU. Here the five local moments (``x, y, x^2, y^2, x y``) are blurred by two vectorised
1-D passes, block of rows by block of rows on the interleaved ``[H, W, C]`` image (no planar copies,
no full-image moment maps: an earlier version that wrote them spent most of its time on memory);
the forward pass also stores ``dS/dmu_x``, ``dS/dE[x^2]`` and ``dS/dE[x y]`` per pixel, and the
backward pass blurs those three maps with the same (symmetric) window:

    dSSIM/dx = (G * dS/dmu_x + 2 x G * dS/dE[x^2] + y G * dS/dE[x y]) / (C H W)

Same value as :func:`plantsplat.train.metrics.ssim` without a mask (tested against a PyTorch
version, values and gradients). Only the prediction gets a gradient.

Example:
    >>> import torch
    >>> x = torch.rand(20, 24, 3)
    >>> round(float(ssim_cpu(x, x)), 5)
    1.0
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
from torch import Tensor

_F32 = np.float32
_FM = {"reassoc", "contract", "arcp", "nsz", "afn"}
_R = 5  # window radius (11 taps)
_C1 = _F32(0.01**2)
_C2 = _F32(0.03**2)


def _window(sigma: float = 1.5) -> np.ndarray:
    g = np.exp(-((np.arange(2 * _R + 1, dtype=np.float64) - _R) ** 2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


_BLOCK = 48  # output rows per parallel task; each task re-blurs 2 * 5 halo rows horizontally


@njit(inline="always", fastmath=_FM)
def _hblur_row(pad, g, c, out, si):  # pragma: no cover - numba
    """out[m, si, :] = horizontal blur of the zero-padded interleaved rows pad[m] (taps c apart)."""
    nm = pad.shape[0]
    n = out.shape[2]
    for m in range(nm):
        o = out[m, si]
        p = pad[m]
        for q in range(n):
            o[q] = _F32(0.0)
        for t in range(g.shape[0]):
            gt = g[t]
            pt = p[c * t:c * t + n]
            for q in range(n):
                o[q] += gt * pt[q]


@njit(inline="always", fastmath=_FM)
def _vblur_row(hb, g, i, s0, h, acc):  # pragma: no cover - numba
    """acc[m, :] = vertical blur at image row i of the horizontally blurred rows hb[m, row - s0, :]
    (rows outside [0, h) are zero)."""
    r = (g.shape[0] - 1) // 2
    nm = hb.shape[0]
    n = hb.shape[2]
    for m in range(nm):
        for q in range(n):
            acc[m, q] = _F32(0.0)
    for t in range(g.shape[0]):
        src = i + t - r
        if src < 0 or src >= h:
            continue
        gt = g[t]
        si = src - s0
        for m in range(nm):
            a = acc[m]
            src_row = hb[m, si]
            for q in range(n):
                a[q] += gt * src_row[q]


@njit(inline="always")
def _block_span(b, h, r):  # pragma: no cover - numba
    """Output rows [i0, i1) of block b and the input rows [s0, s1) its window reaches (halo r, clipped)."""
    i0 = b * _BLOCK
    i1 = min(h, i0 + _BLOCK)
    return i0, i1, max(0, i0 - r), min(h, i1 + r)


@njit(parallel=True, fastmath=_FM, cache=True, error_model="numpy")
def _ssim_fwd(x, y, c, g, want_grad, dmaps, partial):  # pragma: no cover - numba
    """SSIM of interleaved images x, y [H, W*c] (c channels): partial[i] = sum of row i's SSIM map;
    if want_grad, dmaps[0..2, i] = dS/dmu_x, dS/dE[x^2], dS/dE[x y] per pixel and channel.

    Per block of rows: the five local moments (x, y, x^2, y^2, x y) of the block and its halo are
    blurred horizontally into a small buffer, then vertically row by row straight into the SSIM
    formula, so no full-image moment maps are written."""
    h, n = x.shape
    r = (g.shape[0] - 1) // 2
    nblk = (h + _BLOCK - 1) // _BLOCK
    for b in prange(nblk):
        i0, i1, s0, s1 = _block_span(b, h, r)
        pad = np.zeros((5, n + 2 * r * c), np.float32)  # borders stay zero (zero padding)
        hb = np.empty((5, s1 - s0, n), np.float32)
        for row in range(s0, s1):
            for q in range(n):
                a = x[row, q]
                v = y[row, q]
                pad[0, r * c + q] = a
                pad[1, r * c + q] = v
                pad[2, r * c + q] = a * a
                pad[3, r * c + q] = v * v
                pad[4, r * c + q] = a * v
            _hblur_row(pad, g, c, hb, row - s0)
        mu = np.empty((5, n), np.float32)
        for i in range(i0, i1):
            _vblur_row(hb, g, i, s0, h, mu)
            s_row = _F32(0.0)
            for q in range(n):
                mx = mu[0, q]
                my = mu[1, q]
                sxx = mu[2, q] - mx * mx
                syy = mu[3, q] - my * my
                sxy = mu[4, q] - mx * my
                a1 = _F32(2.0) * mx * my + _C1
                a2 = _F32(2.0) * sxy + _C2
                b1 = mx * mx + my * my + _C1
                b2 = sxx + syy + _C2
                s = (a1 * a2) / (b1 * b2)
                s_row += s
                if want_grad:
                    dmaps[0, i, q] = s * _F32(2.0) * (my / a1 - my / a2 - mx / b1 + mx / b2)
                    dmaps[1, i, q] = -s / b2
                    dmaps[2, i, q] = _F32(2.0) * s / a2
            partial[i] = s_row


@njit(parallel=True, fastmath=_FM, cache=True, error_model="numpy")
def _ssim_bwd(dmaps, x, y, c, g, scale, out):  # pragma: no cover - numba
    """out = scale * (G * dmaps[0] + 2 x (G * dmaps[1]) + y (G * dmaps[2])), interleaved [H, W*c]
    (G: the same symmetric window), blocked as :func:`_ssim_fwd`."""
    h, n = x.shape
    r = (g.shape[0] - 1) // 2
    nblk = (h + _BLOCK - 1) // _BLOCK
    for b in prange(nblk):
        i0, i1, s0, s1 = _block_span(b, h, r)
        pad = np.zeros((3, n + 2 * r * c), np.float32)
        hb = np.empty((3, s1 - s0, n), np.float32)
        for row in range(s0, s1):
            for m in range(3):
                for q in range(n):
                    pad[m, r * c + q] = dmaps[m, row, q]
            _hblur_row(pad, g, c, hb, row - s0)
        bd = np.empty((3, n), np.float32)
        for i in range(i0, i1):
            _vblur_row(hb, g, i, s0, h, bd)
            for q in range(n):
                out[i, q] = scale * (bd[0, q] + _F32(2.0) * x[i, q] * bd[1, q] + y[i, q] * bd[2, q])


def _rows(t: Tensor) -> np.ndarray:
    """[H, W, C] tensor -> float32 [H, W*C] array (no copy when already contiguous float32)."""
    a = t.detach().to(torch.float32).contiguous().numpy()
    return a.reshape(a.shape[0], -1)


class _SSIMCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt):
        x = _rows(pred)
        y = _rows(gt)
        h, n = x.shape
        c = pred.shape[2]
        g = _window()
        want = bool(ctx.needs_input_grad[0])
        dmaps = np.empty((3, h, n) if want else (3, 0, 0), np.float32)
        partial = np.empty(h, np.float32)
        _ssim_fwd(x, y, c, g, want, dmaps, partial)
        if want:
            ctx.saved = (x, y, c, dmaps, g, pred.shape)
        return pred.new_tensor(float(partial.astype(np.float64).sum() / (h * n)))

    @staticmethod
    def backward(ctx, g_out):
        x, y, c, dmaps, g, shape = ctx.saved
        h, n = x.shape
        out = np.empty_like(x)
        _ssim_bwd(dmaps, x, y, c, g, _F32(float(g_out) / (h * n)), out)
        return torch.from_numpy(out).view(shape).to(g_out.dtype), None


def ssim_cpu(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean SSIM of two [H, W, C] float images in [0, 1] (11x11 Gaussian window, sigma 1.5, zero
    padding); differentiable with respect to ``pred``. Computed in float32 with numba kernels.

    Example:
        >>> import torch
        >>> a = torch.zeros(16, 16, 3); b = torch.ones(16, 16, 3)
        >>> float(ssim_cpu(a, b)) < 0.01
        True
    """
    if pred.shape != gt.shape or pred.dim() != 3:
        raise ValueError(f"ssim_cpu: need two [H, W, C] images of one shape, got {list(pred.shape)} and "
                         f"{list(gt.shape)}")
    if pred.shape[0] < 1 or pred.shape[1] < 1:
        raise ValueError("ssim_cpu: empty image")
    out = _SSIMCPU.apply(pred, gt)
    return out.to(pred.dtype)


__all__ = ["ssim_cpu"]

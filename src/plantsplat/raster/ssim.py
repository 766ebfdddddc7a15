"""Fused SSIM loss for the CPU: numba kernels for the value and a hand-written gradient.

The training loss ``0.8 L1 + 0.2 (1 - SSIM)`` needs SSIM of the render against the ground truth at
every step. As separable depthwise ``conv2d`` calls in PyTorch (11x11 Gaussian window, sigma 1.5,
zero padding, the usual ``C1 = 0.01^2``, ``C2 = 0.03^2``) it costs more than rasterizing the image
on a CPU. Here the five local moments (``x, y, x^2, y^2, x y``) are blurred by two vectorised
1-D passes; the forward pass also stores ``dS/dmu_x``, ``dS/dE[x^2]`` and ``dS/dE[x y]`` per pixel,
and the backward pass blurs those three maps with the same (symmetric) window:

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


@njit(parallel=True, fastmath=_FM, cache=True)
def _blur(maps, g, out):  # pragma: no cover - numba
    """Separable blur of maps [M, H, W] with the 11-tap window g, zero padding (as conv2d padding=5)."""
    m, h, w = maps.shape
    r = (g.shape[0] - 1) // 2
    tmp = np.zeros((m, h + 2 * r, w), np.float32)  # horizontal pass, rows padded for the vertical one
    for mi in prange(m * h):
        k = mi // h
        i = mi - k * h
        row = np.zeros(w + 2 * r, np.float32)
        row[r:r + w] = maps[k, i]
        acc = np.zeros(w, np.float32)
        for t in range(2 * r + 1):
            gt = g[t]
            for j in range(w):
                acc[j] += gt * row[j + t]
        tmp[k, i + r] = acc
    for mi in prange(m * h):
        k = mi // h
        i = mi - k * h
        acc = np.zeros(w, np.float32)
        for t in range(2 * r + 1):
            gt = g[t]
            src = tmp[k, i + t]
            for j in range(w):
                acc[j] += gt * src[j]
        out[k, i] = acc


@njit(parallel=True, fastmath=_FM, cache=True)
def _moments(x, y, out):  # pragma: no cover - numba
    """out[0..4] = x, y, x^2, y^2, x y for planar images x, y [C, H, W] (out [5, C*H, W])."""
    c, h, w = x.shape
    for ci in prange(c * h):
        k = ci // h
        i = ci - k * h
        for j in range(w):
            a = x[k, i, j]
            b = y[k, i, j]
            out[0, ci, j] = a
            out[1, ci, j] = b
            out[2, ci, j] = a * a
            out[3, ci, j] = b * b
            out[4, ci, j] = a * b


@njit(parallel=True, fastmath=_FM, cache=True)
def _ssim_maps(mu, want_grad, dmaps, partial):  # pragma: no cover - numba
    """SSIM per pixel from the blurred moments mu [5, R, W]; partial[row] = row sums of SSIM; if
    want_grad, dmaps[0..2] = dS/dmu_x, dS/dE[x^2], dS/dE[x y]."""
    _, rows, w = mu.shape
    for i in prange(rows):
        s_row = np.float32(0.0)
        for j in range(w):
            mx = mu[0, i, j]
            my = mu[1, i, j]
            sxx = mu[2, i, j] - mx * mx
            syy = mu[3, i, j] - my * my
            sxy = mu[4, i, j] - mx * my
            a1 = np.float32(2.0) * mx * my + _C1
            a2 = np.float32(2.0) * sxy + _C2
            b1 = mx * mx + my * my + _C1
            b2 = sxx + syy + _C2
            s = (a1 * a2) / (b1 * b2)
            s_row += s
            if want_grad:
                dmaps[0, i, j] = s * np.float32(2.0) * (my / a1 - my / a2 - mx / b1 + mx / b2)
                dmaps[1, i, j] = -s / b2
                dmaps[2, i, j] = np.float32(2.0) * s / a2
        partial[i] = s_row


@njit(parallel=True, fastmath=_FM, cache=True)
def _ssim_grad(bd, x, y, scale, out):  # pragma: no cover - numba
    """out = scale * (bd[0] + 2 x bd[1] + y bd[2]), planar [C, H, W] with bd [3, C*H, W]."""
    c, h, w = x.shape
    for ci in prange(c * h):
        k = ci // h
        i = ci - k * h
        for j in range(w):
            out[k, i, j] = scale * (bd[0, ci, j] + np.float32(2.0) * x[k, i, j] * bd[1, ci, j]
                                    + y[k, i, j] * bd[2, ci, j])


def _planar(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).permute(2, 0, 1).numpy())  # [C, H, W]


class _SSIMCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt):
        x = _planar(pred)
        y = _planar(gt)
        c, h, w = x.shape
        g = _window()
        mom = np.empty((5, c * h, w), np.float32)
        _moments(x, y, mom)
        mu = np.empty_like(mom)
        _blur(mom.reshape(5 * c, h, w), g, mu.reshape(5 * c, h, w))  # per channel plane
        want = bool(ctx.needs_input_grad[0])
        dmaps = np.empty((3, c * h, w) if want else (3, 0, 0), np.float32)
        partial = np.empty(c * h, np.float32)
        _ssim_maps(mu, want, dmaps, partial)
        n = c * h * w
        if want:
            ctx.saved = (x, y, dmaps, g, n)
        return pred.new_tensor(float(partial.astype(np.float64).sum() / n))

    @staticmethod
    def backward(ctx, g_out):
        x, y, dmaps, g, n = ctx.saved
        c, h, w = x.shape
        bd = np.empty_like(dmaps)
        _blur(dmaps.reshape(3 * c, h, w), g, bd.reshape(3 * c, h, w))
        out = np.empty_like(x)
        _ssim_grad(bd, x, y, _F32(float(g_out) / n), out)
        return torch.from_numpy(out).permute(1, 2, 0).contiguous().to(g_out.dtype), None


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

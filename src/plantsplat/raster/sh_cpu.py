"""Spherical-harmonic colours for the CPU backend: numba forward and hand-written backward.

Computes ``max(SH(dir) + 0.5, 0)`` per Gaussian, with ``dir = normalize(mean - camera centre)``,
the same real SH basis (degree 0..3, gsplat / 3DGS signs) as
:func:`plantsplat.raster.projection.spherical_harmonics` followed by the clamp of
:func:`plantsplat.raster.rasterize`, which the ``reference`` backend uses and the tests compare
against (values and gradients). In PyTorch the ~16 basis maps, their products and the autograd
graph cost more than the projection kernel; here one parallel loop over the Gaussians does it.

Gradients flow to the SH coefficients and to the means (through the view direction), not to the
camera. The clamp passes the gradient where ``SH + 0.5 >= 0``, as ``torch.clamp_min``.

Example:
    >>> import torch
    >>> sh = torch.zeros(1, 4, 3); sh[0, 0] = 1.0
    >>> sh_colors_cpu(1, torch.tensor([[0.0, 0.0, 1.0]]), torch.zeros(3), sh)  # 0.5 + SH_C0
    tensor([[0.7821, 0.7821, 0.7821]])
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

import plantsplat.raster.numba_config  # noqa: F401  (numba's threading layer)

from .projection import SH_C0, SH_C1, SH_C2, SH_C3

_F32 = np.float32
_FM = False  # strict IEEE (sums in the reference's order): see plantsplat.raster.numba_config
_C0 = _F32(SH_C0)
_C1 = _F32(SH_C1)
_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = (_F32(c) for c in SH_C2)
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = (_F32(c) for c in SH_C3)
_EPS = _F32(1e-12)  # F.normalize's eps
_HALF = _F32(0.5)
_ZERO = _F32(0.0)
_CHUNK = 256


@njit(inline="always", fastmath=_FM)
def _basis(x, y, z, deg, b):  # pragma: no cover - numba
    """The (deg + 1)^2 basis values at unit direction (x, y, z) into b[0..]."""
    b[0] = _C0
    if deg < 1:
        return
    b[1] = -_C1 * y
    b[2] = _C1 * z
    b[3] = -_C1 * x
    if deg < 2:
        return
    xx = x * x
    yy = y * y
    zz = z * z
    b[4] = _C2_0 * (x * y)
    b[5] = _C2_1 * (y * z)
    b[6] = _C2_2 * (_F32(2.0) * zz - xx - yy)
    b[7] = _C2_3 * (x * z)
    b[8] = _C2_4 * (xx - yy)
    if deg < 3:
        return
    b[9] = _C3_0 * y * (_F32(3.0) * xx - yy)
    b[10] = _C3_1 * (x * y) * z
    b[11] = _C3_2 * y * (_F32(4.0) * zz - xx - yy)
    b[12] = _C3_3 * z * (_F32(2.0) * zz - _F32(3.0) * xx - _F32(3.0) * yy)
    b[13] = _C3_4 * x * (_F32(4.0) * zz - xx - yy)
    b[14] = _C3_5 * z * (xx - yy)
    b[15] = _C3_6 * x * (xx - _F32(3.0) * yy)


@njit(parallel=True, fastmath=_FM, cache=True)
def _sh_fwd(deg, means, campos, coeffs, out):  # pragma: no cover - numba
    """out[n, c] = max(sum_k basis_k(dir_n) coeffs[n, k, c] + 0.5, 0)."""
    n = means.shape[0]
    nb = (deg + 1) * (deg + 1)
    for ch in prange((n + _CHUNK - 1) // _CHUNK):  # chunks: one scratch allocation per chunk
        b = np.empty(16, np.float32)
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            vx = means[i, 0] - campos[0]
            vy = means[i, 1] - campos[1]
            vz = means[i, 2] - campos[2]
            inv = _F32(1.0) / max(np.sqrt(vx * vx + vy * vy + vz * vz), _EPS)
            _basis(vx * inv, vy * inv, vz * inv, deg, b)
            for c in range(3):
                s = _ZERO
                for k in range(nb):
                    s += b[k] * coeffs[i, k, c]
                out[i, c] = max(s + _HALF, _ZERO)


@njit(inline="always", fastmath=_FM)
def _sh_bwd_one(i, deg, nb, means, campos, coeffs, g_out, g_coeffs, g_means, b, w):  # pragma: no cover - numba
    """The backward pass of Gaussian i (b, w: scratch of 16)."""
    vx = means[i, 0] - campos[0]
    vy = means[i, 1] - campos[1]
    vz = means[i, 2] - campos[2]
    inv = _F32(1.0) / max(np.sqrt(vx * vx + vy * vy + vz * vz), _EPS)
    x = vx * inv
    y = vy * inv
    z = vz * inv
    _basis(x, y, z, deg, b)
    gc0 = _ZERO
    gc1 = _ZERO
    gc2 = _ZERO
    for c in range(3):
        s = _ZERO
        for k in range(nb):
            s += b[k] * coeffs[i, k, c]
        gc = g_out[i, c] if s + _HALF >= _ZERO else _ZERO
        for k in range(nb):
            g_coeffs[i, k, c] = b[k] * gc
        if c == 0:
            gc0 = gc
        elif c == 1:
            gc1 = gc
        else:
            gc2 = gc
    if deg < 1:
        g_means[i, 0] = _ZERO
        g_means[i, 1] = _ZERO
        g_means[i, 2] = _ZERO
        return
    # w_k = dL/d basis_k; then dL/d(x, y, z) = sum_k w_k grad(basis_k)
    for k in range(1, nb):
        w[k] = gc0 * coeffs[i, k, 0] + gc1 * coeffs[i, k, 1] + gc2 * coeffs[i, k, 2]
    dx = -_C1 * w[3]
    dy = -_C1 * w[1]
    dz = _C1 * w[2]
    if deg >= 2:
        dx += _C2_0 * y * w[4] + _C2_2 * _F32(-2.0) * x * w[6] + _C2_3 * z * w[7] + _C2_4 * _F32(2.0) * x * w[8]
        dy += _C2_0 * x * w[4] + _C2_1 * z * w[5] + _C2_2 * _F32(-2.0) * y * w[6] + _C2_4 * _F32(-2.0) * y * w[8]
        dz += _C2_1 * y * w[5] + _C2_2 * _F32(4.0) * z * w[6] + _C2_3 * x * w[7]
    if deg >= 3:
        xx = x * x
        yy = y * y
        zz = z * z
        dx += (_C3_0 * _F32(6.0) * x * y * w[9] + _C3_1 * y * z * w[10] + _C3_2 * _F32(-2.0) * x * y * w[11]
               + _C3_3 * _F32(-6.0) * x * z * w[12] + _C3_4 * (_F32(4.0) * zz - _F32(3.0) * xx - yy) * w[13]
               + _C3_5 * _F32(2.0) * x * z * w[14] + _C3_6 * _F32(3.0) * (xx - yy) * w[15])
        dy += (_C3_0 * _F32(3.0) * (xx - yy) * w[9] + _C3_1 * x * z * w[10]
               + _C3_2 * (_F32(4.0) * zz - xx - _F32(3.0) * yy) * w[11] + _C3_3 * _F32(-6.0) * y * z * w[12]
               + _C3_4 * _F32(-2.0) * x * y * w[13] + _C3_5 * _F32(-2.0) * y * z * w[14]
               + _C3_6 * _F32(-6.0) * x * y * w[15])
        dz += (_C3_1 * x * y * w[10] + _C3_2 * _F32(8.0) * y * z * w[11]
               + _C3_3 * (_F32(6.0) * zz - _F32(3.0) * xx - _F32(3.0) * yy) * w[12]
               + _C3_4 * _F32(8.0) * x * z * w[13] + _C3_5 * (xx - yy) * w[14])
    # d = v / max(|v|, eps): dL/dv = (dL/dd - d (d . dL/dd)) / |v|; below eps the denominator is
    # a constant (F.normalize's clamp), so dL/dv = dL/dd / eps
    if vx * vx + vy * vy + vz * vz > _EPS * _EPS:
        dot = x * dx + y * dy + z * dz
        dx -= x * dot
        dy -= y * dot
        dz -= z * dot
    g_means[i, 0] = dx * inv
    g_means[i, 1] = dy * inv
    g_means[i, 2] = dz * inv


@njit(parallel=True, fastmath=_FM, cache=True)
def _sh_bwd(deg, means, campos, coeffs, g_out, g_coeffs, g_means):  # pragma: no cover - numba
    """g_coeffs[n, k, c] = basis_k g_c and g_means[n] = d/d mean through the normalised direction,
    with g_c = g_out[n, c] where SH + 0.5 >= 0 (else 0). g_coeffs must be zero beyond the basis."""
    n = means.shape[0]
    nb = (deg + 1) * (deg + 1)
    for ch in prange((n + _CHUNK - 1) // _CHUNK):
        b = np.empty(16, np.float32)
        w = np.empty(16, np.float32)
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            _sh_bwd_one(i, deg, nb, means, campos, coeffs, g_out, g_coeffs, g_means, b, w)


def _f32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).numpy())


class _SHColorsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, coeffs, campos, degree):
        m, c, cp = _f32(means), _f32(coeffs), _f32(campos)
        out = np.empty((m.shape[0], 3), np.float32)
        _sh_fwd(degree, m, cp, c, out)
        ctx.saved = (m, c, cp, degree, means.dtype, coeffs.dtype)
        return torch.from_numpy(out).to(coeffs.dtype)

    @staticmethod
    def backward(ctx, g_out):
        m, c, cp, degree, mdt, cdt = ctx.saved
        # the kernel writes the first (degree + 1)^2 coefficients' gradients; the others stay zero
        g_c = np.empty_like(c) if c.shape[1] == (degree + 1) ** 2 else np.zeros_like(c)
        g_m = np.empty_like(m)
        _sh_bwd(degree, m, cp, c, _f32(g_out), g_c, g_m)
        g_means = torch.from_numpy(g_m).to(mdt) if ctx.needs_input_grad[0] and degree >= 1 else None
        g_coeffs = torch.from_numpy(g_c).to(cdt) if ctx.needs_input_grad[1] else None
        return g_means, g_coeffs, None, None


def sh_colors_cpu(degree: int, means: Tensor, campos: Tensor, coeffs: Tensor) -> Tensor:
    """RGB ``[N, 3]`` = ``max(SH_degree(normalize(means - campos)) . coeffs + 0.5, 0)``.

    Args:
        degree: 0..3.
        means: ``[N, 3]`` Gaussian centres; campos: ``[3]`` camera centre (no gradient).
        coeffs: ``[N, K, 3]`` SH coefficients, ``K >= (degree + 1)^2`` (extra ones get zero gradient).

    Computed in float32; differentiable with respect to ``means`` (degree >= 1) and ``coeffs``.

    Example:
        >>> import torch
        >>> sh_colors_cpu(0, torch.zeros(2, 3), torch.ones(3), torch.full((2, 1, 3), -5.0)).tolist()
        [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    """
    if not isinstance(degree, int) or not 0 <= degree <= 3:
        raise ValueError(f"sh_colors_cpu: degree must be 0..3, got {degree!r}")
    if means.dim() != 2 or means.shape[1] != 3 or coeffs.dim() != 3 or coeffs.shape[0] != means.shape[0] \
            or coeffs.shape[2] != 3 or coeffs.shape[1] < (degree + 1) ** 2 or campos.shape != (3,):
        raise ValueError(f"sh_colors_cpu: need means [N, 3], campos [3], coeffs [N, >={(degree + 1) ** 2}, 3]; got "
                         f"{list(means.shape)}, {list(campos.shape)}, {list(coeffs.shape)}")
    return _SHColorsCPU.apply(means, coeffs, campos, degree)


__all__ = ["sh_colors_cpu"]

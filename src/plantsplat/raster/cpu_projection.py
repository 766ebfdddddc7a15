"""EWA projection of 3D Gaussians for the CPU backend: numba forward and hand-written backward.

Computes the same quantities as :func:`plantsplat.raster.projection.project_gaussians` (which the
``reference`` backend uses and the tests compare against), one Gaussian per loop iteration in
parallel, so the per-iteration cost is a few milliseconds instead of hundreds of small PyTorch ops
and their autograd graph. Gradients flow to means, quats and scales (not to the camera).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

import plantsplat.raster.numba_config  # noqa: F401  (numba's threading layer)

_F32 = np.float32
_FM = False  # strict IEEE: see plantsplat.raster.numba_config
_ZERO = _F32(0.0)
_HALF = _F32(0.5)
_ONE = _F32(1.0)
_TWO = _F32(2.0)
_ALPHA_MIN = _F32(1.0 / 255.0)
_EXTENT_MAX = _F32(3.33)
_MAX_RADIUS = _F32(1.0e9)


@njit(parallel=True, fastmath=_FM, cache=True)
def _project_fwd(means, quats, scales, opac, view, cam, width, height, near, far, eps2d,
                 out_m2d, out_conic, out_depth, out_radii):  # pragma: no cover - numba
    """cam = (fx, fy, cx, cy); view = [4, 4] world-to-camera. Writes the per-Gaussian outputs."""
    n = means.shape[0]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    tan_x = _HALF * _F32(width) / fx
    tan_y = _HALF * _F32(height) / fy
    lim_xp = (_F32(width) - cx) / fx + _F32(0.3) * tan_x
    lim_xn = cx / fx + _F32(0.3) * tan_x
    lim_yp = (_F32(height) - cy) / fy + _F32(0.3) * tan_y
    lim_yn = cy / fy + _F32(0.3) * tan_y
    for i in prange(n):
        out_radii[i, 0] = 0
        out_radii[i, 1] = 0
        px, py, pz = means[i, 0], means[i, 1], means[i, 2]
        tx = view[0, 0] * px + view[0, 1] * py + view[0, 2] * pz + view[0, 3]
        ty = view[1, 0] * px + view[1, 1] * py + view[1, 2] * pz + view[1, 3]
        tz = view[2, 0] * px + view[2, 1] * py + view[2, 2] * pz + view[2, 3]
        out_depth[i] = tz
        if not (tz >= near and tz <= far):
            out_m2d[i, 0] = _ZERO
            out_m2d[i, 1] = _ZERO
            out_conic[i, 0] = _ZERO
            out_conic[i, 1] = _ZERO
            out_conic[i, 2] = _ZERO
            continue
        # rotation of the Gaussian from the normalised quaternion
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qn = max(qn, _F32(1e-12))
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        R = np.empty((3, 3), np.float32)
        R[0, 0] = _ONE - _TWO * (qy * qy + qz * qz)
        R[0, 1] = _TWO * (qx * qy - qw * qz)
        R[0, 2] = _TWO * (qx * qz + qw * qy)
        R[1, 0] = _TWO * (qx * qy + qw * qz)
        R[1, 1] = _ONE - _TWO * (qx * qx + qz * qz)
        R[1, 2] = _TWO * (qy * qz - qw * qx)
        R[2, 0] = _TWO * (qx * qz - qw * qy)
        R[2, 1] = _TWO * (qy * qz + qw * qx)
        R[2, 2] = _ONE - _TWO * (qx * qx + qy * qy)
        # W = view rotation @ R @ diag(s): camera-space covariance is W W^T
        Wm = np.empty((3, 3), np.float32)
        for r in range(3):
            for c in range(3):
                Wm[r, c] = (view[r, 0] * R[0, c] + view[r, 1] * R[1, c] + view[r, 2] * R[2, c]) * scales[i, c]
        u = min(max(tx / tz, -lim_xn), lim_xp)
        v = min(max(ty / tz, -lim_yn), lim_yp)
        j00 = fx / tz
        j02 = -fx * u / tz
        j11 = fy / tz
        j12 = -fy * v / tz
        # rows of J W (2 x 3)
        a0 = j00 * Wm[0, 0] + j02 * Wm[2, 0]
        a1 = j00 * Wm[0, 1] + j02 * Wm[2, 1]
        a2 = j00 * Wm[0, 2] + j02 * Wm[2, 2]
        b0 = j11 * Wm[1, 0] + j12 * Wm[2, 0]
        b1 = j11 * Wm[1, 1] + j12 * Wm[2, 1]
        b2 = j11 * Wm[1, 2] + j12 * Wm[2, 2]
        ca = a0 * a0 + a1 * a1 + a2 * a2 + eps2d
        cb = a0 * b0 + a1 * b1 + a2 * b2
        cc = b0 * b0 + b1 * b1 + b2 * b2 + eps2d
        det = ca * cc - cb * cb
        mx = fx * tx / tz + cx
        my = fy * ty / tz + cy
        out_m2d[i, 0] = mx
        out_m2d[i, 1] = my
        if not det > _ZERO:
            out_conic[i, 0] = _ZERO
            out_conic[i, 1] = _ZERO
            out_conic[i, 2] = _ZERO
            continue
        out_conic[i, 0] = cc / det
        out_conic[i, 1] = -cb / det
        out_conic[i, 2] = ca / det
        o = opac[i]
        if o < _ALPHA_MIN:
            continue
        ext = min(_EXTENT_MAX, math.sqrt(_TWO * math.log(max(o / _ALPHA_MIN, _ONE))))
        rx = min(math.ceil(ext * math.sqrt(max(ca, _ZERO))), _MAX_RADIUS)
        ry = min(math.ceil(ext * math.sqrt(max(cc, _ZERO))), _MAX_RADIUS)
        if rx <= 0 and ry <= 0:
            continue
        if mx + rx <= 0 or mx - rx >= width or my + ry <= 0 or my - ry >= height:
            continue
        out_radii[i, 0] = np.int32(rx)
        out_radii[i, 1] = np.int32(ry)


@njit(parallel=True, fastmath=_FM, cache=True)
def _project_bwd(means, quats, scales, view, cam, width, height, radii, v_m2d, v_conic, v_depth,
                 out_vmeans, out_vquats, out_vscales):  # pragma: no cover - numba
    """Backward of _project_fwd for the visible Gaussians (radii > 0); others get zero gradients."""
    n = means.shape[0]
    fx, fy = cam[0], cam[1]
    cx, cy = cam[2], cam[3]
    tan_x = _HALF * _F32(width) / fx
    tan_y = _HALF * _F32(height) / fy
    lim_xp = (_F32(width) - cx) / fx + _F32(0.3) * tan_x
    lim_xn = cx / fx + _F32(0.3) * tan_x
    lim_yp = (_F32(height) - cy) / fy + _F32(0.3) * tan_y
    lim_yn = cy / fy + _F32(0.3) * tan_y
    for i in prange(n):
        for k in range(3):
            out_vmeans[i, k] = _ZERO
            out_vscales[i, k] = _ZERO
        for k in range(4):
            out_vquats[i, k] = _ZERO
        if radii[i, 0] <= 0 or radii[i, 1] <= 0:
            continue
        px, py, pz = means[i, 0], means[i, 1], means[i, 2]
        tx = view[0, 0] * px + view[0, 1] * py + view[0, 2] * pz + view[0, 3]
        ty = view[1, 0] * px + view[1, 1] * py + view[1, 2] * pz + view[1, 3]
        tz = view[2, 0] * px + view[2, 1] * py + view[2, 2] * pz + view[2, 3]
        qw0, qx0, qy0, qz0 = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        qn = max(math.sqrt(qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0), _F32(1e-12))
        qw, qx, qy, qz = qw0 / qn, qx0 / qn, qy0 / qn, qz0 / qn
        R = np.empty((3, 3), np.float32)
        R[0, 0] = _ONE - _TWO * (qy * qy + qz * qz)
        R[0, 1] = _TWO * (qx * qy - qw * qz)
        R[0, 2] = _TWO * (qx * qz + qw * qy)
        R[1, 0] = _TWO * (qx * qy + qw * qz)
        R[1, 1] = _ONE - _TWO * (qx * qx + qz * qz)
        R[1, 2] = _TWO * (qy * qz - qw * qx)
        R[2, 0] = _TWO * (qx * qz - qw * qy)
        R[2, 1] = _TWO * (qy * qz + qw * qx)
        R[2, 2] = _ONE - _TWO * (qx * qx + qy * qy)
        Wm = np.empty((3, 3), np.float32)  # view rotation @ R @ diag(s)
        VR = np.empty((3, 3), np.float32)  # view rotation @ R
        for r in range(3):
            for c in range(3):
                VR[r, c] = view[r, 0] * R[0, c] + view[r, 1] * R[1, c] + view[r, 2] * R[2, c]
                Wm[r, c] = VR[r, c] * scales[i, c]
        ux = tx / tz
        uy = ty / tz
        u = min(max(ux, -lim_xn), lim_xp)
        v = min(max(uy, -lim_yn), lim_yp)
        x_in = ux == u  # not clamped
        y_in = uy == v
        j00 = fx / tz
        j02 = -fx * u / tz
        j11 = fy / tz
        j12 = -fy * v / tz
        A = np.empty(3, np.float32)  # first row of J W
        B = np.empty(3, np.float32)  # second row of J W
        for c in range(3):
            A[c] = j00 * Wm[0, c] + j02 * Wm[2, c]
            B[c] = j11 * Wm[1, c] + j12 * Wm[2, c]
        ca = A[0] * A[0] + A[1] * A[1] + A[2] * A[2] + cam[4]  # cam[4] = eps2d
        cb = A[0] * B[0] + A[1] * B[1] + A[2] * B[2]
        cc = B[0] * B[0] + B[1] * B[1] + B[2] * B[2] + cam[4]
        det = ca * cc - cb * cb
        id2 = _ONE / (det * det)
        gA, gB, gC = v_conic[i, 0], v_conic[i, 1], v_conic[i, 2]
        # conic = (cc, -cb, ca) / det  ->  gradients w.r.t. the 2D covariance entries
        g_a = (-cc * cc * gA + cb * cc * gB - cb * cb * gC) * id2
        g_b = (_TWO * cb * cc * gA - (det + _TWO * cb * cb) * gB + _TWO * ca * cb * gC) * id2
        g_c = (-cb * cb * gA + ca * cb * gB - ca * ca * gC) * id2
        # cov2d = [[A.A, A.B], [A.B, B.B]]: dL/dA = 2 g_a A + g_b B, dL/dB = g_b A + 2 g_c B
        gAv = np.empty(3, np.float32)
        gBv = np.empty(3, np.float32)
        for c in range(3):
            gAv[c] = _TWO * g_a * A[c] + g_b * B[c]
            gBv[c] = g_b * A[c] + _TWO * g_c * B[c]
        # A = j00 W0 + j02 W2, B = j11 W1 + j12 W2
        gj00 = gAv[0] * Wm[0, 0] + gAv[1] * Wm[0, 1] + gAv[2] * Wm[0, 2]
        gj02 = gAv[0] * Wm[2, 0] + gAv[1] * Wm[2, 1] + gAv[2] * Wm[2, 2]
        gj11 = gBv[0] * Wm[1, 0] + gBv[1] * Wm[1, 1] + gBv[2] * Wm[1, 2]
        gj12 = gBv[0] * Wm[2, 0] + gBv[1] * Wm[2, 1] + gBv[2] * Wm[2, 2]
        gW = np.empty((3, 3), np.float32)
        for c in range(3):
            gW[0, c] = j00 * gAv[c]
            gW[1, c] = j11 * gBv[c]
            gW[2, c] = j02 * gAv[c] + j12 * gBv[c]
        # J entries w.r.t. camera-space mean (txc = tz * clamp(tx / tz))
        itz = _ONE / tz
        itz2 = itz * itz
        g_tx = _ZERO
        g_ty = _ZERO
        g_tz = -fx * itz2 * gj00 - fy * itz2 * gj11
        if x_in:  # j02 = -fx tx / tz^2
            g_tx += -fx * itz2 * gj02
            g_tz += _TWO * fx * tx * itz2 * itz * gj02
        else:  # j02 = -fx u / tz with u constant
            g_tz += fx * u * itz2 * gj02
        if y_in:
            g_ty += -fy * itz2 * gj12
            g_tz += _TWO * fy * ty * itz2 * itz * gj12
        else:
            g_tz += fy * v * itz2 * gj12
        # means2d = (fx tx / tz + cx, fy ty / tz + cy), depth = tz
        gmx, gmy = v_m2d[i, 0], v_m2d[i, 1]
        g_tx += fx * itz * gmx
        g_ty += fy * itz * gmy
        g_tz += -fx * tx * itz2 * gmx - fy * ty * itz2 * gmy + v_depth[i]
        for k in range(3):
            out_vmeans[i, k] = view[0, k] * g_tx + view[1, k] * g_ty + view[2, k] * g_tz
        # W = Rv R diag(s): dL/ds_c = sum_r gW[r, c] (Rv R)[r, c]; dL/dR = Rv^T (gW diag(s))
        for c in range(3):
            out_vscales[i, c] = gW[0, c] * VR[0, c] + gW[1, c] * VR[1, c] + gW[2, c] * VR[2, c]
        G = np.empty((3, 3), np.float32)
        for r in range(3):
            for c in range(3):
                G[r, c] = (view[0, r] * gW[0, c] + view[1, r] * gW[1, c] + view[2, r] * gW[2, c]) * scales[i, c]
        dw = _TWO * (-qz * G[0, 1] + qy * G[0, 2] + qz * G[1, 0] - qx * G[1, 2] - qy * G[2, 0] + qx * G[2, 1])
        dx = _TWO * (qy * G[0, 1] + qz * G[0, 2] + qy * G[1, 0] - _TWO * qx * G[1, 1] - qw * G[1, 2]
                     + qz * G[2, 0] + qw * G[2, 1] - _TWO * qx * G[2, 2])
        dy = _TWO * (-_TWO * qy * G[0, 0] + qx * G[0, 1] + qw * G[0, 2] + qx * G[1, 0] + qz * G[1, 2]
                     - qw * G[2, 0] + qz * G[2, 1] - _TWO * qy * G[2, 2])
        dz = _TWO * (-_TWO * qz * G[0, 0] - qw * G[0, 1] + qx * G[0, 2] + qw * G[1, 0] - _TWO * qz * G[1, 1]
                     + qy * G[1, 2] + qx * G[2, 0] + qy * G[2, 1])
        # through the normalisation q / |q|
        dot = dw * qw + dx * qx + dy * qy + dz * qz
        out_vquats[i, 0] = (dw - dot * qw) / qn
        out_vquats[i, 1] = (dx - dot * qx) / qn
        out_vquats[i, 2] = (dy - dot * qy) / qn
        out_vquats[i, 3] = (dz - dot * qz) / qn


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).numpy())


def _camera_arrays(viewmat: Tensor, K: Tensor, eps2d: float):
    view = _np32(viewmat)  # [4, 4]
    Kn = K.detach().double()
    cam = np.array([Kn[0, 0], Kn[1, 1], Kn[0, 2], Kn[1, 2], eps2d], np.float32)
    return view, cam


def _run_fwd(means, quats, scales, opacities, view, cam, width, height, near, far):
    n = means.shape[0]
    m2d = np.empty((n, 2), np.float32)
    conic = np.empty((n, 3), np.float32)
    depth = np.empty(n, np.float32)
    radii = np.empty((n, 2), np.int32)
    if n:
        _project_fwd(_np32(means), _np32(quats), _np32(scales), _np32(opacities), view, cam, width, height,
                     _F32(near), _F32(min(far, 3.0e38)), cam[4], m2d, conic, depth, radii)
    return m2d, conic, depth, radii


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d):
        view, cam = _camera_arrays(viewmat, K, eps2d)
        m2d, conic, depth, radii = _run_fwd(means, quats, scales, opacities, view, cam, width, height, near, far)
        ctx.save_for_backward(means, quats, scales)
        ctx.cam = (view, cam, width, height, radii)
        dt = means.dtype
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        return torch.from_numpy(m2d).to(dt), torch.from_numpy(conic).to(dt), torch.from_numpy(depth).to(dt), radii_t

    @staticmethod
    def backward(ctx, v_m2d, v_conic, v_depth, _v_radii):
        means, quats, scales = ctx.saved_tensors
        view, cam, width, height, radii = ctx.cam
        n = means.shape[0]
        vm = np.zeros((n, 3), np.float32)
        vq = np.zeros((n, 4), np.float32)
        vs = np.zeros((n, 3), np.float32)
        if n:
            z2 = np.zeros((n, 2), np.float32)
            z3 = np.zeros((n, 3), np.float32)
            z1 = np.zeros(n, np.float32)
            _project_bwd(_np32(means), _np32(quats), _np32(scales), view, cam, width, height, radii,
                         z2 if v_m2d is None else _np32(v_m2d), z3 if v_conic is None else _np32(v_conic),
                         z1 if v_depth is None else _np32(v_depth), vm, vq, vs)
        dt = means.dtype
        return (torch.from_numpy(vm).to(dt), torch.from_numpy(vq).to(dt), torch.from_numpy(vs).to(dt),
                None, None, None, None, None, None, None, None)


def project_cpu(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """numba version of :func:`plantsplat.raster.projection.project_gaussians` (same outputs).

    Returns means2d [N, 2], conics [N, 3], depths [N], radii [N, 2] int32; differentiable with
    respect to means, quats and scales.

    Example:
        >>> m2d, con, z, r = project_cpu(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...     torch.full((1, 3), 0.05), torch.tensor([0.9]), torch.eye(4),
        ...     torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]), 64, 64)
        >>> m2d.tolist(), z.tolist(), r.tolist()
        ([[32.0, 32.0]], [2.0], [[9, 9]])
    """
    if torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, scales)):
        return _ProjectCPU.apply(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
    view, cam = _camera_arrays(viewmat, K, eps2d)
    m2d, conic, depth, radii = _run_fwd(means, quats, scales, opacities, view, cam, width, height, near, far)
    dt = means.dtype
    return (torch.from_numpy(m2d).to(dt), torch.from_numpy(conic).to(dt), torch.from_numpy(depth).to(dt),
            torch.from_numpy(radii))

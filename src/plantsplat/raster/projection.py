"""EWA projection of 3D Gaussians and spherical-harmonics colours in plain PyTorch.

These differentiable functions follow gsplat's conventions (``fully_fused_projection`` with a pinhole
camera, ``spherical_harmonics``), so the CPU and CUDA backends agree. They are shared by the
``reference`` and ``cpu`` backends: autograd differentiates them; only the per-pixel compositing of
the ``cpu`` backend has a hand-written backward (``plantsplat.raster.cpu``).

Conventions (as gsplat):

- ``viewmat`` is world-to-camera with OpenCV axes (x right, y down, z forward), ``K`` is pinhole.
- 2D covariance ``J W Sigma W^T J^T`` with the Jacobian's ``x/z`` and ``y/z`` clamped to 1.3x the
  field of view, plus ``eps2d * I`` (low-pass dilation); conic = inverse 2D covariance ``(a, b, c)``
  so that ``sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy`` with ``d = mean2d - pixel_centre``.
- Per-axis screen radii ``ceil(e * sqrt(cov2d_ii))`` with the opacity-aware extent
  ``e = min(3.33, sqrt(2 ln(255 opacity)))``; a Gaussian is culled (radius 0) when its depth is not in
  ``[near, far]``, its opacity is below 1/255, its 2D covariance is degenerate, or its box misses
  the image.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
# Radii are clamped here before the int32 cast (huge Gaussians cover the whole image anyway).
_MAX_RADIUS = 1.0e9

# Real spherical-harmonics constants (degree 0..3), the same basis and signs as gsplat / 3DGS.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from (not necessarily unit) wxyz quaternions.

    Example:
        >>> R = quat_to_rotmat(torch.tensor([[2.0, 0.0, 0.0, 0.0]]))  # [1, 3, 3] identity
    """
    q = F.normalize(quats, p=2, dim=-1)  # [N, 4]
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )  # [N, 9]
    return R.reshape(quats.shape[:-1] + (3, 3))


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariances ``R S S^T R^T`` ([N, 3, 3]) from quaternions [N, 4] and scales [N, 3].

    Example:
        >>> C = quat_scale_to_covar(torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[1.0, 2.0, 3.0]]))
        >>> torch.diagonal(C[0]).tolist()
        [1.0, 4.0, 9.0]
    """
    M = quat_to_rotmat(quats) * scales[..., None, :]  # [N, 3, 3]
    return M @ M.transpose(-1, -2)


def project_gaussians(
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
    """Project 3D Gaussians to the image plane (differentiable, gsplat conventions).

    Returns ``means2d`` [N, 2] (pixels), ``conics`` [N, 3] (inverse 2D covariance a, b, c),
    ``depths`` [N] (camera z) and ``radii`` [N, 2] int32 (0 = culled). Values of culled Gaussians
    are finite but meaningless.

    Example:
        >>> m2d, con, z, r = project_gaussians(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...     torch.full((1, 3), 0.05), torch.tensor([0.9]), torch.eye(4),
        ...     torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]), 64, 64)
        >>> m2d.tolist(), z.tolist()
        ([[32.0, 32.0]], [2.0])
    """
    R = viewmat[:3, :3]  # [3, 3]
    t = viewmat[:3, 3]  # [3]
    means_c = means @ R.T + t  # [N, 3]
    covars = quat_scale_to_covar(quats, scales)  # [N, 3, 3]
    covars_c = R @ covars @ R.T  # [N, 3, 3]

    tx, ty, tz = means_c.unbind(-1)  # [N]
    depth_ok = (tz >= near) & (tz <= far)  # [N]
    # Culled Gaussians (behind the camera, z == 0) get a harmless depth so nothing divides by zero:
    # torch.where sends no gradient to the unused branch.
    tz_s = torch.where(depth_ok, tz, torch.ones_like(tz))  # [N]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    txc = tz_s * torch.minimum(torch.maximum(tx / tz_s, -lim_x_neg), lim_x_pos)  # [N]
    tyc = tz_s * torch.minimum(torch.maximum(ty / tz_s, -lim_y_neg), lim_y_pos)  # [N]
    zero = torch.zeros_like(tz_s)
    J = torch.stack(
        [fx / tz_s, zero, -fx * txc / (tz_s * tz_s), zero, fy / tz_s, -fy * tyc / (tz_s * tz_s)], dim=-1
    ).reshape(-1, 2, 3)  # [N, 2, 3]
    cov2d = J @ covars_c @ J.transpose(-1, -2)  # [N, 2, 2]
    means2d = torch.stack([fx * tx / tz_s + cx, fy * ty / tz_s + cy], dim=-1)  # [N, 2]

    a = cov2d[:, 0, 0] + eps2d  # [N]
    b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])  # [N]
    c = cov2d[:, 1, 1] + eps2d  # [N]
    det = a * c - b * b  # [N]
    det_ok = det > 0
    det_s = torch.where(det_ok, det, torch.ones_like(det))  # [N]
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)  # [N, 3]

    with torch.no_grad():
        op = opacities.detach()
        extend = torch.sqrt(2.0 * torch.log(torch.clamp(op / ALPHA_THRESHOLD, min=1.0)))
        extend = torch.clamp(extend, max=3.33)  # [N]
        rx = torch.ceil(extend * torch.sqrt(torch.clamp(a.detach(), min=0.0))).clamp(max=_MAX_RADIUS)  # [N]
        ry = torch.ceil(extend * torch.sqrt(torch.clamp(c.detach(), min=0.0))).clamp(max=_MAX_RADIUS)  # [N]
        mx, my = means2d.detach().unbind(-1)
        valid = depth_ok & det_ok & (op >= ALPHA_THRESHOLD) & ((rx > 0) | (ry > 0))
        valid &= (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        radii = torch.stack([rx, ry], dim=-1)  # [N, 2]
        radii = torch.where(valid[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return means2d, conics, tz, radii


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate real SH of ``degree`` (0..3) at directions ``dirs`` [N, 3] (need not be unit).

    ``coeffs`` is [N, K, 3] with K >= (degree + 1)^2; returns [N, 3] (before gsplat's +0.5 and clamp).

    Example:
        >>> sh = torch.zeros(1, 4, 3); sh[0, 0] = 1.0
        >>> spherical_harmonics(1, torch.tensor([[0.0, 0.0, 1.0]]), sh)  # SH_C0 * 1
        tensor([[0.2821, 0.2821, 0.2821]])
    """
    n_basis = (degree + 1) ** 2
    if degree < 1:
        return SH_C0 * coeffs[:, 0]  # [N, 3]
    d = F.normalize(dirs, p=2, dim=-1)  # [N, 3]
    x, y, z = d.unbind(-1)  # [N] each
    basis = [torch.full_like(x, SH_C0), -SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                  SH_C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    B = torch.stack(basis, dim=-1)  # [N, n_basis]
    return torch.bmm(B[:, None, :], coeffs[:, :n_basis]).squeeze(1)  # [N, 3]

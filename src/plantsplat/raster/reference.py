"""Slow, obviously correct pure-PyTorch compositing (autograd does the backward).

Each tile's pixels are compared with every Gaussian listed for the tile (dense ``[P, G]``
matrices, one tile at a time), so it is slow and memory-hungry: it is the ground truth the fast
``cpu`` backend is tested against. It applies
exactly the rules of gsplat's tile rasterizer:

- Gaussians are composited front to back in order of camera depth;
- a Gaussian reaches a pixel only if the pixel's ``tile_size`` tile lies in the Gaussian's tile box
  ``[floor((mean - r) / ts), ceil((mean + r) / ts))`` (per axis, r = screen radius);
- pixel centres are at ``(x + 0.5, y + 0.5)``; ``alpha = min(0.999, o * exp(-sigma))``, skipped when
  ``sigma < 0`` or ``alpha < 1/255``;
- a pixel stops at the first Gaussian that would bring its transmittance to ``<= 1e-4`` (that
  Gaussian is not composited).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import ALPHA_THRESHOLD

_T_EPS = 1e-4


def tile_boxes(means2d: Tensor, radii: Tensor, tile_size: int, tiles_x: int, tiles_y: int) -> Tensor:
    """Tile boxes ``[N, 4]`` int64 (x0, y0, x1, y1; x1/y1 exclusive) as gsplat's tile intersection.

    Example:
        >>> tile_boxes(torch.tensor([[20.0, 20.0]]), torch.tensor([[5, 5]]), 16, 4, 4).tolist()
        [[0, 0, 2, 2]]
    """
    m = means2d.detach().float() / tile_size  # [N, 2]
    r = radii.float() / tile_size  # [N, 2]
    lo = torch.floor(m - r)  # [N, 2]
    hi = torch.ceil(m + r)  # [N, 2]
    lim = torch.tensor([tiles_x, tiles_y], dtype=m.dtype)
    lo = torch.minimum(torch.clamp(lo, min=0), lim)
    hi = torch.minimum(torch.clamp(hi, min=0), lim)
    return torch.cat([lo, hi], dim=-1).to(torch.int64)  # [N, 4]


def composite_reference(
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
    """Composite projected Gaussians densely; returns colour [H, W, 3], alpha [H, W, 1], sum z*w [H, W, 1].

    Example:
        >>> c, a, d = composite_reference(torch.tensor([[4.0, 4.0]]), torch.tensor([[1.0, 0.0, 1.0]]),
        ...     torch.ones(1, 3), torch.tensor([0.5]), torch.tensor([2.0]), torch.tensor([[3, 3]]), 8, 8)
        >>> c.shape, a.shape, d.shape
        (torch.Size([8, 8, 3]), torch.Size([8, 8, 1]), torch.Size([8, 8, 1]))
    """
    dtype = means2d.dtype
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    vis = (radii > 0).all(dim=-1)  # [N]
    idx = torch.nonzero(vis).flatten()  # [G]
    idx = idx[torch.argsort(depths.detach()[idx], stable=True)]  # front to back
    m, con, col = means2d[idx], conics[idx], colors[idx]  # [G, 2], [G, 3], [G, 3]
    op, z = opacities[idx], depths[idx]  # [G], [G]
    box = tile_boxes(m, radii[idx], tile_size, tiles_x, tiles_y)  # [G, 4]

    # One tile at a time (results are identical to one dense [H*W, G] matrix, which would not fit
    # in memory for large scenes): only the Gaussians whose tile box holds the tile are composited.
    parts_idx, parts_c, parts_a, parts_d = [], [], [], []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            sel = torch.nonzero((box[:, 0] <= tx) & (tx < box[:, 2]) & (box[:, 1] <= ty) & (ty < box[:, 3])).flatten()
            y0, x0 = ty * tile_size, tx * tile_size
            ys, xs = torch.meshgrid(torch.arange(y0, min(y0 + tile_size, height)),
                                    torch.arange(x0, min(x0 + tile_size, width)), indexing="ij")
            ys, xs = ys.reshape(-1, 1), xs.reshape(-1, 1)  # [P, 1]
            parts_idx.append((ys * width + xs).flatten())
            c, a, d = _composite_pixels(xs.to(dtype) + 0.5, ys.to(dtype) + 0.5, m[sel], con[sel], col[sel],
                                        op[sel], z[sel])
            parts_c.append(c)
            parts_a.append(a)
            parts_d.append(d)
    idx = torch.cat(parts_idx)  # [H*W] pixel index of each row below
    color = torch.zeros(height * width, 3, dtype=dtype).index_copy(0, idx, torch.cat(parts_c))
    acc = torch.zeros(height * width, 1, dtype=dtype).index_copy(0, idx, torch.cat(parts_a))
    depth_sum = torch.zeros(height * width, 1, dtype=dtype).index_copy(0, idx, torch.cat(parts_d))
    return color.reshape(height, width, 3), acc.reshape(height, width, 1), depth_sum.reshape(height, width, 1)


def _composite_pixels(px, py, m, con, col, op, z):
    """Front-to-back compositing of depth-sorted Gaussians [G] over pixel centres px, py [P, 1]."""
    dx = m[:, 0] - px  # [P, G]
    dy = m[:, 1] - py  # [P, G]
    sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy  # [P, G]
    alpha = torch.clamp(op * torch.exp(-sigma), max=0.999)  # [P, G]
    used = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)  # [P, G]
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - alpha, dim=1)  # [P, G] transmittance after each Gaussian
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], dim=1)  # [P, G]
    stopped = torch.cumsum((T_after <= _T_EPS).to(torch.int32), dim=1) > 0  # [P, G]
    w = torch.where(stopped, torch.zeros_like(alpha), alpha * T_before)  # [P, G] blending weights
    return w @ col, w.sum(dim=1, keepdim=True), w @ z[:, None]

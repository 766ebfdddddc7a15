"""The ``gsplat`` backend: gsplat's CUDA ``rasterization()`` behind plantsplat's interface."""

from __future__ import annotations

import torch
from torch import Tensor

from . import RasterInputError, RenderResult


def rasterize_gsplat(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3] or [N, K, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    sh_degree: int | None,
    near: float,
    far: float,
    eps2d: float,
    tile_size: int,
):
    """Render with ``gsplat.rasterization`` (CUDA tensors) and return a :class:`RenderResult`.

    ``means2d`` of the result is a [N, 2] tensor whose ``.grad`` is filled, after ``backward()``,
    from gsplat's [1, N, 2] projected means (gsplat needs a camera batch dimension).

    Usage:
        out = rasterize_gsplat(means.cuda(), quats.cuda(), ...)
    """
    from gsplat import rasterization  # deferred: gsplat is optional (CUDA only)

    if means.device.type != "cuda":
        raise RasterInputError(f"rasterize: backend 'gsplat' needs CUDA tensors, got {means.device}")
    render, alphas, meta = rasterization(
        means, quats, scales, opacities, colors, viewmat[None], K[None], width, height,
        near_plane=near, far_plane=far, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        tile_size=tile_size, render_mode="RGB+ED",
    )  # [1, H, W, 4], [1, H, W, 1]
    means2d_b = meta["means2d"]  # [1, N, 2]
    proxy = means2d_b.detach()[0]  # [N, 2]; its .grad is set by the hook below
    if means2d_b.requires_grad:

        def _hook(g: Tensor) -> None:
            proxy.grad = g[0].detach().clone() if proxy.grad is None else proxy.grad + g[0]

        means2d_b.register_hook(_hook)
    radii2 = meta["radii"][0]  # [N, 2] (gsplat >= 1.5) or [N]
    if radii2.dim() == 1:
        radii2 = radii2[:, None].expand(-1, 2)
    visible = (radii2 > 0).all(dim=-1)  # [N]
    radii = torch.where(visible, radii2.max(dim=-1).values, torch.zeros_like(radii2[:, 0]))
    return RenderResult(color=render[0, ..., :3], alpha=alphas[0], depth=render[0, ..., 3:4],
                        means2d=proxy, radii=radii.to(torch.int32), visible=visible)

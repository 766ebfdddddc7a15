"""Differentiable 3D Gaussian rasterization with one interface and three backends.

- ``cpu``: numba kernels with hand-written backward passes: EWA projection parallel over Gaussians
  (:mod:`plantsplat.raster.cpu_projection`), SH colours parallel over Gaussians
  (:mod:`plantsplat.raster.sh_cpu`), compositing parallel over 16x16 tiles and vectorised
  over the pixels of a tile (:mod:`plantsplat.raster.cpu`). The default without CUDA.
- ``gsplat``: gsplat's CUDA ``rasterization()`` (:mod:`plantsplat.raster.gsplat_backend`), chosen by
  ``auto`` when CUDA and gsplat are available.
- ``reference``: slow pure-PyTorch compositing differentiated by autograd
  (:mod:`plantsplat.raster.reference`), the ground truth of the tests.

All backends follow gsplat's conventions (pinhole EWA projection with ``eps2d`` dilation,
opacity-aware screen radii, 16x16 tiles, pixel centres at +0.5, alpha clamped to 0.999 and skipped
below 1/255, transmittance stop at 1e-4, SH colours ``max(SH(dir) + 0.5, 0)``).

Example:
    >>> import torch
    >>> from plantsplat.raster import rasterize
    >>> N = 100
    >>> out = rasterize(torch.randn(N, 3) * 0.3 + torch.tensor([0, 0, 3.0]), torch.randn(N, 4),
    ...                 torch.full((N, 3), 0.05), torch.full((N,), 0.8), torch.rand(N, 3),
    ...                 torch.eye(4), torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]), 64, 48)
    >>> out.color.shape, out.alpha.shape, out.depth.shape, out.radii.dtype
    (torch.Size([48, 64, 3]), torch.Size([48, 64, 1]), torch.Size([48, 64, 1]), torch.int32)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import PlantsplatError
from .projection import project_gaussians, spherical_harmonics
from .reference import composite_reference

__all__ = ["RenderResult", "RasterInputError", "rasterize", "resolve_backend", "BACKENDS"]

BACKENDS = ("auto", "cpu", "gsplat", "reference")


class RasterInputError(PlantsplatError, ValueError):
    """Invalid rasterizer input: wrong shapes or dtypes, NaN/Inf parameters, impossible sizes.

    NaN policy: any non-finite value in means, quats, scales, opacities, colours, the camera or the
    intrinsics raises this error before a kernel runs (a diverged training step must be handled by
    the caller, for example by lowering the learning rate or restoring a checkpoint).
    """


@dataclass
class RenderResult:
    """Output of :func:`rasterize`.

    Attributes:
        color: [H, W, 3] ``sum_i c_i a_i T_i`` (not composited over any background).
        alpha: [H, W, 1] accumulated opacity ``sum_i a_i T_i = 1 - T_final``.
        depth: [H, W, 1] expected camera-z depth ``sum_i z_i a_i T_i / alpha`` (gsplat "ED";
            0 where alpha == 0).
        means2d: [N, 2] projected centres in pixels; when gradients are enabled its ``.grad``
            holds d loss / d pixel position after ``backward()`` (for density control).
        radii: [N] int32 screen radius in pixels (max over x/y), 0 = culled / not visible.
        visible: [N] bool, ``radii > 0``.
    """

    color: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor


@functools.lru_cache(maxsize=1)
def _gsplat_available() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401  (deferred: gsplat is optional, CUDA only)
    except Exception:  # gsplat missing or broken install
        return False
    return True


def resolve_backend(backend: str = "auto") -> str:
    """Resolve ``auto`` to ``gsplat`` (CUDA and gsplat importable) or ``cpu``; check explicit names.

    Example:
        >>> resolve_backend("cpu")
        'cpu'
    """
    if backend not in BACKENDS:
        raise RasterInputError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "gsplat" if _gsplat_available() else "cpu"
    if backend == "gsplat" and not _gsplat_available():
        raise PlantsplatError(
            "backend 'gsplat' needs an NVIDIA GPU with CUDA PyTorch and `pip install gsplat`; "
            "use --backend cpu (or auto) on this machine"
        )
    return backend


def _check_tensor(name: str, t: object, shape: tuple, dtype_float: bool = True) -> tuple[float, float] | None:
    """Type, shape, dtype and finiteness checks; returns (min, max) of a non-empty float tensor."""
    if not isinstance(t, Tensor):
        raise RasterInputError(f"rasterize: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise RasterInputError(f"rasterize: {name} has shape {list(t.shape)}, expected {want}")
    if dtype_float and not t.is_floating_point():
        raise RasterInputError(f"rasterize: {name} must be a floating-point tensor, got {t.dtype}")
    if not t.numel():
        return None
    d = t.detach()
    if d.is_floating_point():
        # min and max propagate NaN and show +-Inf: one pass, no [N, ...] bool temporary
        # (isfinite().all() took 18 ms on [200k, 16, 3] SH coefficients, aminmax 1.4 ms)
        lo, hi = (float(v) for v in torch.aminmax(d))
        if math.isfinite(lo) and math.isfinite(hi):
            return lo, hi
    elif bool(torch.isfinite(d).all()):
        return None
    bad = int((~torch.isfinite(d)).sum())
    raise RasterInputError(
        f"rasterize: {name} has {bad} NaN/Inf value(s); training diverged or the model file is "
        "corrupt: lower the learning rate or restore the last good checkpoint"
    )


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, near, far,
              eps2d, tile_size) -> None:
    _check_tensor("means", means, (None, 3))
    N = means.shape[0]
    _check_tensor("quats", quats, (N, 4))
    s_range = _check_tensor("scales", scales, (N, 3))
    o_range = _check_tensor("opacities", opacities, (N,))
    if sh_degree is None:
        _check_tensor("colors", colors, (N, 3))
    else:
        if not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
            raise RasterInputError(f"rasterize: sh_degree must be None or 0..3, got {sh_degree!r}")
        _check_tensor("colors (SH coefficients)", colors, (N, None, 3))
        if colors.shape[1] < (sh_degree + 1) ** 2:
            raise RasterInputError(
                f"rasterize: sh_degree={sh_degree} needs at least {(sh_degree + 1) ** 2} SH coefficients "
                f"per Gaussian, colors has {colors.shape[1]}"
            )
    _check_tensor("viewmat", viewmat, (4, 4))
    _check_tensor("K", K, (3, 3))
    for name, v in (("width", width), ("height", height), ("tile_size", tile_size)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise RasterInputError(f"rasterize: {name} must be a positive int, got {v!r}")
    if width * height > 2**30:
        raise RasterInputError(f"rasterize: image {width}x{height} is too large")
    if not (0.0 <= near < far):
        raise RasterInputError(f"rasterize: need 0 <= near < far, got near={near}, far={far}")
    if not eps2d >= 0.0:
        raise RasterInputError(f"rasterize: eps2d must be >= 0, got {eps2d}")
    if s_range is not None and s_range[0] < 0:
        raise RasterInputError("rasterize: scales must be positive (pass exp(log_scales))")
    if o_range is not None and (o_range[0] < 0 or o_range[1] > 1):
        raise RasterInputError("rasterize: opacities must lie in [0, 1] (pass sigmoid(logits))")
    devs = {t.device for t in (means, quats, scales, opacities, colors, viewmat, K)}
    if len(devs) > 1:
        raise RasterInputError(f"rasterize: all tensors must be on one device, got {sorted(map(str, devs))}")


def rasterize(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3] or [N, K, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    sh_degree: int | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    backend: str = "auto",
    tile_size: int = 16,
    trailing_background: int = 0,
) -> RenderResult:
    """Render N 3D Gaussians into one ``height`` x ``width`` pinhole view, differentiably.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z), normalised here.
        scales: [N, 3] positive axis scales (already exp'd).
        opacities: [N] in [0, 1] (already sigmoid'ed).
        colors: [N, 3] RGB, or [N, K, 3] SH coefficients when ``sh_degree`` is given
            (K >= (sh_degree + 1)^2; view directions from the camera centre; colour
            ``max(SH + 0.5, 0)`` as gsplat).
        viewmat: [4, 4] world-to-camera, OpenCV axes (x right, y down, z forward).
        K: [3, 3] pinhole intrinsics in pixels.
        width, height: image size in pixels.
        sh_degree: None for plain RGB colours, else 0..3.
        near, far: depth range kept (camera z).
        eps2d: low-pass dilation added to the 2D covariances.
        backend: ``auto`` | ``cpu`` | ``gsplat`` | ``reference``.
        tile_size: tile edge in pixels (16 as gsplat).
        trailing_background: the last this many Gaussians are coloured exactly as the background the
            caller will composite the image over (``color + (1 - alpha) * bg``; the trainer's
            occluders). Where nothing else lies behind them they change neither that composite nor
            any gradient, so the cpu backend drops them from the end of each tile's list: same
            composite and gradients, less work; ``alpha`` and ``depth`` alone then leave them out
            there. Other backends draw them all.

    Gradients flow to means, quats, scales, opacities and colors (SH coefficients); the cpu
    backend does not differentiate with respect to the camera (viewmat, K). Under
    ``torch.no_grad()`` the cpu backend skips the bookkeeping for the backward pass. The cpu
    backend computes in float32 (float64 inputs are rounded) and needs ``tile_size`` to be a
    multiple of 8 up to 32. Bad shapes, non-finite values and impossible sizes raise
    :class:`RasterInputError`; N = 0 renders an empty (transparent) image.

    Example:
        >>> import torch
        >>> out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...                 torch.full((1, 3), 0.1), torch.tensor([0.9]), torch.ones(1, 3), torch.eye(4),
        ...                 torch.tensor([[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]]), 32, 32, backend="cpu")
        >>> round(float(out.alpha[16, 16, 0]), 3), round(float(out.depth[16, 16, 0]), 3)
        (0.866, 2.0)
    """
    _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, near, far,
              eps2d, tile_size)
    if isinstance(trailing_background, bool) or not isinstance(trailing_background, int) \
            or not 0 <= trailing_background <= means.shape[0]:
        raise RasterInputError(f"rasterize: trailing_background must be an int in 0..N={means.shape[0]}, "
                               f"got {trailing_background!r}")
    backend = resolve_backend(backend)
    if backend == "gsplat":
        from .gsplat_backend import rasterize_gsplat  # deferred: gsplat is optional (CUDA only)

        return rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                sh_degree, near, far, eps2d, tile_size)

    if means.device.type != "cpu":
        raise RasterInputError(f"rasterize: backend {backend!r} needs CPU tensors, got {means.device}")
    # the reference uses the autograd projection, the cpu backend its numba twin (tested against it)
    if backend == "reference":
        project = project_gaussians
    else:
        from .cpu_projection import project_cpu as project  # deferred: numba, which only the cpu backend needs
    means2d, conics, depths, radii2 = project(
        means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d
    )  # [N, 2], [N, 3], [N], [N, 2]
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]  # [3] camera centre in world
        if backend == "reference":
            rgb = torch.clamp_min(spherical_harmonics(sh_degree, means - campos, colors) + 0.5, 0.0)  # [N, 3]
        else:  # the same colours and gradients from numba kernels (tested against the line above)
            from .sh_cpu import sh_colors_cpu  # deferred: numba, which only the cpu backend needs

            rgb = sh_colors_cpu(sh_degree, means, campos.detach(), colors)  # [N, 3]
    else:
        rgb = colors  # [N, 3]
    if means2d.requires_grad:
        means2d.retain_grad()

    if backend == "reference":
        color, alpha, depth_sum = composite_reference(
            means2d, conics, rgb, opacities, depths, radii2, width, height, tile_size
        )
    else:
        from .cpu import composite_cpu  # deferred: numba, which only the cpu backend needs

        color, alpha, depth_sum = composite_cpu(
            means2d, conics, rgb, opacities, depths, radii2, width, height, tile_size,
            first_background=means.shape[0] - trailing_background,
        )
    depth = depth_sum / torch.clamp(alpha, min=1e-10)  # [H, W, 1] gsplat "ED"
    visible = (radii2 > 0).all(dim=-1)  # [N]
    radii = torch.where(visible, radii2.max(dim=-1).values, torch.zeros_like(radii2[:, 0]))  # [N]
    return RenderResult(color=color, alpha=alpha, depth=depth, means2d=means2d,
                        radii=radii.to(torch.int32), visible=visible)

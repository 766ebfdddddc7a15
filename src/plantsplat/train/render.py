"""Rendering a model into a view, the training images at several resolutions, and the occluders.

Shared by the training loop (:mod:`plantsplat.train.trainer`), the evaluation
(:mod:`plantsplat.train.evaluate`) and the segmenter's quick model.

Example:
    >>> import torch
    >>> foreground_box(torch.zeros(4, 6, 1))
    (0, 0, 6, 4)
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from plantsplat.raster import rasterize
from plantsplat.train import data as D
from plantsplat.train.model import rgb_to_sh

# Occluders start opaque and at half the model's initial size (half the mean distance to their 3 nearest
# SfM neighbours): they stand for solid pot and soil. Pixels the plant leaves partly transparent go on
# through the occluders behind it, and wide, half-transparent occluders made every such pixel composite
# many of them: at 0.5 opacity and full size they added 75 % to the composited pairs, at 0.99 and half
# size 47 % (seed 0 of the training benchmark, 2025-11: 2000 steps 169 s -> 153 s, whole-frame and
# foreground PSNR within 0.1 dB).
OCCLUDER_OPACITY = 0.99
OCCLUDER_SCALE = 0.5


class ImageCache:
    """Per view, per downscale factor: image ``[h, w, 3]`` and alpha ``[h, w, 1]`` float tensors."""

    def __init__(self, views: list[D.View], base_scale: float, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.views = {v.name: v for v in views}
        self.base_scale = base_scale  # full resolution -> largest training resolution
        self._cache: dict[tuple[str, int], tuple] = {}
        self._boxes: dict[tuple[str, int], tuple[int, int, int, int]] = {}

    def box(self, name: str, down: int) -> tuple[int, int, int, int]:
        """:func:`foreground_box` of a view's alpha at one downscale (computed once)."""
        key = (name, down)
        if key not in self._boxes:
            img, alpha = self.get(name, down)[:2]
            self._boxes[key] = foreground_box(alpha) if alpha is not None else (0, 0, img.shape[1], img.shape[0])
        return self._boxes[key]

    def get(self, name: str, down: int):
        key = (name, down)
        if key not in self._cache:
            v = self.views[name]
            s = self.base_scale / down
            w, h = max(1, round(v.width * s)), max(1, round(v.height * s))
            interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
            img = cv2.resize(v.image, (w, h), interpolation=interp) if (w, h) != (v.width, v.height) else v.image
            img_t = torch.from_numpy(np.ascontiguousarray(img)).float() / 255.0  # [h, w, 3]
            if v.mask is not None:
                m = cv2.resize(v.mask, (w, h), interpolation=interp) if (w, h) != (v.width, v.height) else v.mask
                a_t = torch.from_numpy(np.ascontiguousarray(m)).float()[..., None] / 255.0  # [h, w, 1]
            else:
                a_t = None
            K = v.K.copy()
            K[0, :] *= w / v.width
            K[1, :] *= h / v.height
            dev = self.device
            self._cache[key] = (img_t.to(dev), None if a_t is None else a_t.to(dev),
                                torch.tensor(K, dtype=torch.float32, device=dev), w, h)
        return self._cache[key]


def foreground_box(alpha: torch.Tensor, margin_frac: float = 0.08, min_margin: int = 8) -> tuple[int, int, int, int]:
    """Bounding box ``(x0, y0, x1, y1)`` of ``alpha > 0`` ``[h, w, 1]`` grown by a margin; the whole
    image when the mask is empty."""
    h, w = alpha.shape[:2]
    ys, xs = torch.nonzero(alpha[..., 0] > 0.01, as_tuple=True)
    if len(xs) == 0:
        return 0, 0, w, h
    mx = max(min_margin, int(margin_frac * w))
    my = max(min_margin, int(margin_frac * h))
    x0, x1 = max(0, int(xs.min()) - mx), min(w, int(xs.max()) + 1 + mx)
    y0, y1 = max(0, int(ys.min()) - my), min(h, int(ys.max()) + 1 + my)
    return x0, y0, x1, y1


def render(params, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, sh_degree: int, backend: str,
           occluders=None, bg: torch.Tensor | None = None):
    """Rasterize the model's Gaussians (activating the parameters) into one view.

    ``occluders`` (object mode; means, scales, quats, opacities like ``params``) are drawn after the
    model's Gaussians in the list, in the background colour ``bg`` ``[3]``: composited over ``bg``
    they look like background, but hide what lies behind them. The result's per-Gaussian outputs
    (``means2d``, ``radii``) then cover the model's Gaussians first, the occluders after them. With
    occluders, use the result only composited over ``bg``: the cpu backend drops occluders with nothing
    of the model behind them (``trailing_background``), which leaves that composite and every gradient
    as they were but not ``alpha`` alone.
    """
    k = (sh_degree + 1) ** 2
    colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], dim=1)  # [N, k, 3]
    means, quats, scales, opac = params["means"], params["quats"], params["scales"], params["opacities"]
    m = 0
    if occluders is not None and occluders["means"].shape[0]:
        m = occluders["means"].shape[0]
        occ_col = torch.zeros(m, k, 3, device=colors.device, dtype=colors.dtype)
        occ_col[:, 0] = rgb_to_sh(bg.to(colors.dtype))  # colour = 0.5 + C0 sh0 = bg; higher bands 0
        colors = torch.cat([colors, occ_col])
        means = torch.cat([means, occluders["means"]])
        quats = torch.cat([quats, occluders["quats"]])
        scales = torch.cat([scales, occluders["scales"]])
        opac = torch.cat([opac, occluders["opacities"]])
    # occluders with nothing of the model behind them change neither the composite over bg nor a gradient
    return rasterize(means, quats, torch.exp(scales), torch.sigmoid(opac), colors, viewmat, K, width, height,
                     sh_degree=sh_degree, backend=backend, trailing_background=m)


def occluder_tensors(p) -> dict | None:
    """Detached copies of the geometry of a parameter dict (occluders: no colours), or None."""
    if p is None:
        return None
    return {k: p[k].detach().clone().cpu() for k in ("means", "scales", "quats", "opacities")}


def occluders_from(t: dict | None, device) -> torch.nn.ParameterDict | None:
    """Occluder parameters from :func:`occluder_tensors`' dict (None: no occluders)."""
    if not t or not t["means"].shape[0]:
        return None
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v.clone().to(device)) for k, v in t.items()})

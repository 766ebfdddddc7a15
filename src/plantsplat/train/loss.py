"""The training loss: L1 and SSIM of a render composited over a background (the paper's RGBA masking),
and the clean-up of non-finite gradients.

Example:
    >>> import torch
    >>> c, a, bg = torch.zeros(16, 16, 3), torch.ones(16, 16, 1), torch.zeros(3)
    >>> float(photometric_loss(c, a, bg, torch.zeros(16, 16, 3), 0.2)[0])
    0.0
"""

from __future__ import annotations

import torch

from plantsplat.raster.ssim import photometric_loss_cpu
from plantsplat.train.metrics import ssim as ssim_torch


def photometric_loss(color: torch.Tensor, alpha: torch.Tensor, bg: torch.Tensor, gt: torch.Tensor,
                     ssim_lambda: float, gt_alpha: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The training loss of a render (``color`` ``[H, W, 3]``, ``alpha`` ``[H, W, 1]``) composited
    over ``bg`` ``[3]``: ``(1 - l) L1 + l (1 - SSIM)`` against ``gt``, and the mean squared error
    (detached, for the progress bar's PSNR). With ``gt_alpha`` (object mode) the target is ``gt``
    composited over the same background through it, ``gt gt_alpha + (1 - gt_alpha) bg``.

    On the CPU: the fused numba kernels of :mod:`plantsplat.raster.ssim` (compositing, L1, SSIM and
    their gradients in two passes; same value and gradients as the PyTorch composition, tested). The
    PyTorch version took about half of a training step at 896 px, and its elementwise operations
    alone a fifth. Elsewhere (CUDA, or a ``gt`` or ``bg`` that needs a gradient, which the fused
    kernels do not give): the PyTorch composition with :func:`plantsplat.train.metrics.ssim`.
    """
    if (color.device.type == "cpu" and gt.device.type == "cpu" and not gt.requires_grad and not bg.requires_grad
            and color.shape[-1] == 3 and (gt_alpha is None or not gt_alpha.requires_grad)):
        return photometric_loss_cpu(color, alpha, bg, gt, ssim_lambda, gt_alpha)
    if gt_alpha is not None:
        gt = gt * gt_alpha + (1.0 - gt_alpha) * bg
    pred = color + (1.0 - alpha) * bg
    loss = (1 - ssim_lambda) * (pred - gt).abs().mean() + ssim_lambda * (1 - ssim_torch(pred, gt))
    return loss, ((pred.detach() - gt.detach()) ** 2).mean()


# A step whose gradients have NaN/inf entries has those Gaussians' gradients zeroed (Adam's update of them is
# then its momentum alone, finite); training stops as diverged only when this lasts this many steps in a row.
MAX_NONFINITE_RUN = 20


def drop_nonfinite_grads(groups, means2d) -> tuple[int, list[str]]:
    """Zero every gradient of the Gaussians that have a NaN/inf gradient entry; returns their number and
    the parameters it was found in.

    ``groups`` are ``(label, ParameterDict or None)`` in the render's order (the model, then the occluders), whose
    rows are Gaussians; ``means2d`` is the render's screen-space means (its gradient feeds the density
    strategy, so it is cleaned too). One NaN in a pixel's gradient reaches every Gaussian drawn there, and a
    single such step used to leave NaN means after Adam's update, which stopped the run (``training
    diverged``) although the loss was finite. A finite sum of a gradient means it has no NaN/inf: the
    per-entry check runs only when a sum is not finite, and all sums are read at once (one GPU sync a step).
    """
    g2 = getattr(means2d, "grad", None)
    parts, offset = [], 0
    for label, p in groups:
        if p is None:
            continue
        n = p["means"].shape[0]
        grads = [(k, t.grad) for k, t in p.items() if t.grad is not None]
        if g2 is not None and g2.shape[0] >= offset + n:
            grads.append(("means2d", g2[offset:offset + n]))
        parts.append((label, n, grads))
        offset += n
    sums = [g.sum() for _, _, grads in parts for _, g in grads]
    if not sums:
        return 0, []
    finite = torch.isfinite(torch.stack(sums))
    if bool(finite.all()):
        return 0, []
    finite = iter(finite.tolist())  # in the order of the sums
    total, where = 0, []
    for label, n, grads in parts:
        bad = None
        for k, g in grads:
            if next(finite):
                continue
            rows = ~torch.isfinite(g).reshape(n, -1).all(dim=1)
            if bool(rows.any()):
                bad = rows if bad is None else bad | rows
                where.append(label + k)
        if bad is not None:
            for _, g in grads:
                g[bad] = 0.0
            total += int(bad.sum())
    return total, where

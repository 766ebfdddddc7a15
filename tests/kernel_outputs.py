"""Writes the CPU kernels' outputs on one fixed scene to an .npz (``python tests/kernel_outputs.py OUT.npz``).

Used by ``test_raster.py`` to compare a process that compiles the numba kernels with one that loads them
from numba's cache: a training step (full and object-mode loss), its gradients and a no-grad render.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from plantsplat.train.loss import photometric_loss
from plantsplat.train.render import render


def outputs() -> dict[str, np.ndarray]:
    g = torch.Generator().manual_seed(5)
    n, w, h = 3000, 96, 72
    params = {
        "means": torch.randn(n, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0]),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) * 0.3 - 3.5,
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g) * 0.5,
        "shN": torch.randn(n, 3, 3, generator=g) * 0.2,
    }
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    K = torch.tensor([[80.0, 0.0, 48.3], [0.0, 81.0, 35.8], [0.0, 0.0, 1.0]])
    view = torch.eye(4)
    bg = torch.tensor([0.3, 0.5, 0.7])
    gt = torch.rand(h + 6, w + 8, 3, generator=g)
    gt_alpha = (torch.rand(h + 6, w + 8, 1, generator=g) > 0.5).float()
    out = {}
    for tag, target, mask in (("full", gt[:h, :w], None), ("object", gt[3:3 + h, 4:4 + w], gt_alpha[3:3 + h, 4:4 + w])):
        r = render(params, view, K, w, h, 1, "cpu", None, bg)
        loss, _ = photometric_loss(r.color, r.alpha, bg, target, 0.2, mask)
        loss.backward()
        out[f"{tag}_color"] = r.color.detach().numpy()
        for k, p in params.items():
            out[f"{tag}_grad_{k}"] = p.grad.numpy().copy()
            p.grad = None
    with torch.no_grad():
        r = render(params, view, K, w, h, 1, "cpu", None, bg)
    out["render_color"], out["render_alpha"] = r.color.numpy(), r.alpha.numpy()
    return out


if __name__ == "__main__":
    np.savez(sys.argv[1], **outputs())

"""The CPU kernels compiled before a run needs them: ``python -m plantsplat.train.warmup``.

numba compiles the rasterizer's and the loss's kernels the first time a process calls them and keeps them in its
cache on disk; later processes load them. The first run after an install therefore compiled them inside the segment
stage, on one core while the other waited: that stage took 120 s instead of 57 s on the demo's capture (2-core AMD
EPYC, 2026-11-30). Where the kernels are not known to be cached (:mod:`plantsplat.kernel_cache`), ``plantsplat run``
and ``plantsplat demo`` start this process when they begin (:func:`plantsplat.pipeline.start_kernel_warmup`): it
compiles the kernels beside the frames and poses stages and then leaves the stamp that says they are cached. It is
never waited for: a stage that reaches a kernel before this process has cached it compiles that kernel itself, as
it would without it. A kernel compiled here is the one the stage would have compiled, bit for bit (the flags of
:mod:`plantsplat.raster.numba_config`; ``tests/test_raster.py`` compares a fresh kernel with a cached one).
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from plantsplat.kernel_cache import mark_kernels_cached
from plantsplat.raster.cpu_projection import project_cpu
from plantsplat.train.loss import photometric_loss
from plantsplat.train.metrics import scored_ssim_map
from plantsplat.train.model import init_params
from plantsplat.train.render import OCCLUDER_OPACITY, OCCLUDER_SCALE, occluder_tensors, occluders_from, render
from plantsplat.workers import worker_start

WIDTH, HEIGHT = 48, 32
"""The tiny view every kernel is called on: three tiles across, two down."""


def _tiny_scene():
    """A few Gaussians before the camera, occluders, a frame, its mask and a camera: ``(params, occ, img, alpha,
    viewmat, K)``, the types the stages use (float32, on the CPU)."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(64, 3)) * 0.3 + np.array([0.0, 0.0, 3.0])
    params = init_params(pts, rng.random((64, 3)), sh_degree=2, init_opacity=0.5, seed=0)
    occ = occluders_from(occluder_tensors(init_params(pts[:16] + 0.05, np.full((16, 3), 0.5), 0, OCCLUDER_OPACITY,
                                                      init_scale=OCCLUDER_SCALE, seed=1)), torch.device("cpu"))
    img = torch.from_numpy(rng.random((HEIGHT, WIDTH, 3))).float()
    alpha = torch.from_numpy(rng.random((HEIGHT, WIDTH, 1)) > 0.5).float()
    K = torch.tensor([[40.0, 0.0, WIDTH / 2], [0.0, 40.0, HEIGHT / 2], [0.0, 0.0, 1.0]])
    return params, occ, img, alpha, torch.eye(4), K


def compile_kernels() -> None:
    """Call every CPU kernel that training (object and full mode), the segment stage's quick model and priors, and
    the evaluation call, through the functions they call it with and with the same argument types, so that numba
    compiles (or loads) each one."""
    params, occ, img, alpha, viewmat, K = _tiny_scene()
    bg = torch.tensor([0.2, 0.5, 0.7])
    x0, y0, x1, y1 = 4, 2, WIDTH - 4, HEIGHT - 2  # object mode renders a crop of the frame
    Kc = K.clone()
    Kc[0, 2] -= x0
    Kc[1, 2] -= y0
    for occluders, gt_alpha in ((occ, alpha[y0:y1, x0:x1]), (None, None)):  # object mode, then full mode
        out = render(params, viewmat, Kc, x1 - x0, y1 - y0, 2, "cpu", occluders, bg)
        loss, _ = photometric_loss(out.color, out.alpha, bg, img[y0:y1, x0:x1], 0.2, gt_alpha)
        loss.backward()
    with torch.no_grad():  # the evaluation and the segment stage's priors render without a gradient
        out = render(params, viewmat, K, WIDTH, HEIGHT, 2, "cpu", occ, bg)
        scored_ssim_map((out.color + (1 - out.alpha) * bg).clamp(0, 1), img)
        project_cpu(params["means"], params["quats"], torch.exp(params["scales"]),
                    torch.sigmoid(params["opacities"]).reshape(-1), viewmat, K, WIDTH, HEIGHT)


def main(argv: list[str]) -> int:
    worker_start()
    torch.set_num_threads(1)
    compile_kernels()
    mark_kernels_cached()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

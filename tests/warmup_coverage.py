"""Whether :func:`plantsplat.train.warmup.compile_kernels` reaches every kernel signature a run uses
(``python tests/warmup_coverage.py WS``, ``WS`` a workspace with frames, masks and poses).

In one process: the warm-up first, then what the stages do on the CPU (an object-mode training with its crops and
evaluation, a full-mode training like the segment stage's quick model, the segment stage's priors and footprints).
The workspace has no SfM points, so its training has no occluders: their one kernel of their own (``_trim_tails``)
is called by the warm-up, through the same ``render``, but not checked here.
numba adds a signature to a kernel whenever it compiles or loads one; prints, as JSON, the signatures the stages'
calls added after the warm-up (none when it reached them all)."""

from __future__ import annotations

import plantsplat  # noqa: F401 (first: it sets OpenMP's and numba's threading up before torch and numba load)

# isort: split
import json
import sys
from pathlib import Path

import numba
import torch

from plantsplat.raster import cpu, cpu_order, cpu_projection, sh_cpu, ssim
from plantsplat.segment.object3d import footprints, render_values
from plantsplat.train import data as D
from plantsplat.train.checkpoint import load_model
from plantsplat.train.config import TrainConfig
from plantsplat.train.trainer import train_workspace
from plantsplat.train.warmup import compile_kernels
from plantsplat.workspace import Workspace


def signatures() -> dict[str, set[str]]:
    return {f"{m.__name__}.{name}": {str(s) for s in obj.signatures}
            for m in (cpu, cpu_order, cpu_projection, sh_cpu, ssim) for name, obj in vars(m).items()
            if isinstance(obj, numba.core.registry.CPUDispatcher)}


def run_stages(ws: Workspace) -> None:
    train_workspace(ws, TrainConfig(iterations=12, max_resolution=96, num_downscales=1, init_points=500, seed=0))
    train_workspace(ws, TrainConfig(mode="full", iterations=6, max_resolution=64, num_downscales=0, sh_degree=1,
                                    evaluate=False, train_dir=ws.root / "train_full"))
    params, _ = load_model(ws)
    view = D.load_scene(ws, need_masks=False).views[0]
    with torch.no_grad():
        render_values(params, torch.rand(params["means"].shape[0], 3), view, scale=0.5)
        footprints(params, view)


def main(argv: list[str]) -> int:
    compile_kernels()
    before = signatures()
    run_stages(Workspace(Path(argv[0])))
    added = {k: sorted(v - before.get(k, set())) for k, v in signatures().items() if v - before.get(k, set())}
    print(json.dumps(added))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

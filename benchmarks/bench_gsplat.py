"""Benchmark of the CUDA path: gsplat's rasterizer against plantsplat's CPU kernels, on a machine with a GPU.

The scenes of ``bench_raster.py`` (``a``: 20k Gaussians at 256x256, ``b``: 100k at 480x270, ``c``: 200k at
960x540) are drawn by both backends through :func:`plantsplat.raster.rasterize`, with the same loss
(colour against fixed random weights, plus alpha). Recorded per case: the largest colour and alpha
difference, the relative error of each parameter's gradient (gsplat against the CPU kernels, which
are themselves checked against the pure-torch reference in ``tests/test_raster.py``), and the median
forward+backward time of each backend (CUDA timed after synchronising). Without CUDA or gsplat it
says so and exits 2.

Writes ``benchmarks/results/gsplat.json`` (or ``--out``) with machine information and the date.

Usage:
    python benchmarks/bench_gsplat.py [--cases a,b,c] [--reps 5] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "gsplat.json"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "src"))

from bench_raster import SYNTH, synth_scene  # noqa: E402  (the same scenes as the CPU benchmark)


def _timed(fn, reps: int, sync) -> float:
    """Median seconds of ``fn()`` over ``reps`` runs after one warm-up."""
    fn()
    sync()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return sorted(ts)[len(ts) // 2]


def run_case(name: str, reps: int) -> dict:
    """One scene through both backends: differences of images and gradients, and times."""
    import torch

    from plantsplat.raster import rasterize

    n, W, H, per_px = SYNTH[name]
    params, V, K = synth_scene(n, W, H, per_px)
    gw = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1))

    def step(device: str, backend: str):
        ps = [p.detach().clone().to(device).requires_grad_(True) for p in params]
        out = rasterize(*ps, V.to(device), K.to(device), W, H, backend=backend)
        ((out.color * gw.to(device)).sum() + out.alpha.sum()).backward()
        return out, ps

    cpu_out, cpu_ps = step("cpu", "cpu")
    gpu_out, gpu_ps = step("cuda", "gsplat")
    names = ("means", "quats", "scales", "opacities", "colors")
    grads = {k: float((g.grad.cpu() - c.grad).norm() / c.grad.norm().clamp_min(1e-12))
             for k, g, c in zip(names, gpu_ps, cpu_ps)}
    return {
        "gaussians": n, "width": W, "height": H,
        "max_color_diff": float((gpu_out.color.detach().cpu() - cpu_out.color.detach()).abs().max()),
        "max_alpha_diff": float((gpu_out.alpha.detach().cpu() - cpu_out.alpha.detach()).abs().max()),
        "grad_rel_error": grads,
        "gsplat_fwd_bwd_s": _timed(lambda: step("cuda", "gsplat"), reps, torch.cuda.synchronize),
        "cpu_fwd_bwd_s": _timed(lambda: step("cpu", "cpu"), reps, lambda: None),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="a,b,c")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULT)
    args = ap.parse_args()
    import torch

    try:
        import gsplat
    except ImportError:
        print("bench_gsplat: gsplat is not installed (pip install 'plantsplat[gpu]')", file=sys.stderr)
        return 2
    if not torch.cuda.is_available():
        print("bench_gsplat: no CUDA device on this machine", file=sys.stderr)
        return 2
    from plantsplat.io import write_json_atomic

    info = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__, "cuda": torch.version.cuda,
            "gsplat": gsplat.__version__, "cpu_threads": torch.get_num_threads(), "python": platform.python_version(),
            "platform": platform.platform()}
    cases = {}
    for name in [c for c in args.cases.split(",") if c]:
        cases[name] = run_case(name, args.reps)
        print(name, json.dumps(cases[name]), flush=True)
    write_json_atomic(args.out, {"benchmark": "gsplat", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                                 "machine": info, "cases": cases})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

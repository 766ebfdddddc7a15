"""Training configuration and presets (light: no torch import at module level).

Example:
    >>> cfg = TrainConfig(mode="object", iterations=500)
    >>> cfg.mode
    'object'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from plantsplat.errors import PlantsplatError

PRESETS = ("cpu", "paper")


@dataclass
class TrainConfig:
    """Training options (``plantsplat train``). ``None`` fields take the preset's value."""

    mode: Literal["object", "full"] = "object"
    """object: RGBA supervision with random backgrounds (the paper's method); full: whole-frame RGB 3DGS (Splatfacto baseline)."""
    backend: Literal["auto", "cpu", "gsplat"] = "auto"
    """Rasterizer: auto = gsplat with CUDA, else the numba CPU backend."""
    preset: Literal["auto", "cpu", "paper"] = "auto"
    """Recipe: cpu = few iterations, resolution schedule, foreground crops; paper = 30k iterations (gsplat).
    auto = paper on CUDA, cpu otherwise."""
    iterations: int | None = None
    """Training steps (cpu preset: 2000, paper: 30000)."""
    test_fraction: float = 0.4
    """Fraction of frames held out for testing (paper: 60/40), evenly spaced."""
    test_every: int = 0
    """Hold out every k-th frame instead of --test-fraction (0 = off)."""
    sh_degree: int | None = None
    """Final spherical-harmonic degree (cpu: 2, paper: 3); raised by one every sh-interval steps."""
    max_resolution: int | None = None
    """Longest image side used for training and evaluation, px (cpu: 960, paper: no limit)."""
    num_downscales: int | None = None
    """Start at 1/2^k resolution and double it on a schedule (cpu: 2, paper: 2 as splatfacto)."""
    crop: bool | None = None
    """Object mode: render only the foreground's bounding box (plus a margin) during training (cpu: on)."""
    occluders: bool = True
    """Object mode: SfM points the masks leave out near the object (pot, soil) become occluders, Gaussians
    drawn in the background colour that hide what they stand in front of (the cube behind the pot), so
    the model is not asked to show it there. Never exported; used by the evaluation's renders."""
    max_gaussians: int | None = None
    """Cap on the number of Gaussians (cpu: 200000, paper: none)."""
    init_points: int = 20_000
    """Random initial Gaussians when the SfM points are too few."""
    seed: int = 0
    """Random seed (split, initialisation, backgrounds)."""
    checkpoint_seconds: float = 60.0
    """Write a checkpoint at least this often (seconds); an interrupted run resumes from it."""
    threads: int = 1
    """Threads for torch's own CPU ops (the loss, the optimiser); the rasterizer's numba kernels use all
    cores regardless. 1 is fastest on small images and busy machines (measured); 0 = every core the process may use
    (a batch worker's share)."""
    evaluate: bool = True
    """Compute PSNR/SSIM/LPIPS, render FPS and memory on the test views after training."""
    lpips_weights: Path | None = None
    """LPIPS(alex) weights file (default: $PLANTSPLAT_LPIPS_WEIGHTS, the lpips package, ../shared/weights)."""
    train_dir: Path | None = None
    """Where split, checkpoints and the model go (default WS/train)."""
    metrics_path: Path | None = None
    """Where metrics are written (default WS/metrics.json)."""

    def resolved(self) -> ResolvedConfig:
        from plantsplat.raster import resolve_backend  # deferred: it loads torch, and the CLI imports this module

        backend = resolve_backend(self.backend)
        preset = self.preset if self.preset != "auto" else ("paper" if backend == "gsplat" else "cpu")
        paper = preset == "paper"
        r = ResolvedConfig(
            mode=self.mode,
            backend=backend,
            preset=preset,
            iterations=self.iterations if self.iterations is not None else (30_000 if paper else 2000),
            sh_degree=self.sh_degree if self.sh_degree is not None else (3 if paper else 2),
            max_resolution=self.max_resolution if self.max_resolution is not None else (0 if paper else 960),
            num_downscales=self.num_downscales if self.num_downscales is not None else 2,
            crop=self.crop if self.crop is not None else (not paper),
            max_gaussians=self.max_gaussians if self.max_gaussians is not None else (0 if paper else 200_000),
            seed=self.seed,
            # the compressed CPU schedule culls early: start opaque enough not to lose everything at once
            init_opacity=0.1 if paper else 0.5,
        )
        if r.iterations < 1:
            raise PlantsplatError(f"--iterations {r.iterations}: must be at least 1", exit_code=2)
        if not 0 <= r.sh_degree <= 3:
            raise PlantsplatError(f"--sh-degree {r.sh_degree}: must be 0..3", exit_code=2)
        if not 0.0 < self.test_fraction < 1.0 and not self.test_every:
            raise PlantsplatError(f"--test-fraction {self.test_fraction}: must be between 0 and 1", exit_code=2)
        return r


@dataclass
class ResolvedConfig:
    """The recipe actually used (stored in checkpoints and metrics)."""

    mode: str
    backend: str
    preset: str
    iterations: int
    sh_degree: int
    max_resolution: int
    num_downscales: int
    crop: bool
    max_gaussians: int
    seed: int
    ssim_lambda: float = 0.2
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    init_opacity: float = 0.1
    strategy: dict = field(default_factory=dict)

    def schedule(self) -> dict:
        """Step numbers of the schedules, scaled to the iteration count (splatfacto's at 30k)."""
        n = self.iterations
        if self.preset == "paper":
            return {"sh_interval": 1000, "res_interval": 3000, "refine_start": 500, "refine_stop": 15_000,
                    "refine_every": 100, "reset_every": 3000}
        # CPU recipe: the same shape compressed into `n` steps
        return {
            "sh_interval": max(1, int(0.1 * n)),
            "res_interval": max(1, int(0.15 * n)),
            # refining before ~100 steps only churns (measured: the loss rose over 80-step runs)
            "refine_start": max(100, int(0.1 * n)),
            "refine_stop": int(0.7 * n),
            "refine_every": max(50, int(n / 40)),
            "reset_every": 0 if n < 1500 else int(0.35 * n),
        }



"""Synthetic workspaces for the report's tests and its viewer's benchmark (``benchmarks/bench_report.py``).

:func:`make_synthetic_workspace` writes every file the report reads, in the formats the real stages
write them: a plant-like cloud of Gaussians (pot, stem, leaves, red fruit) and a 10 cm cube in an
Inria-layout PLY, its centres as a point cloud, frames with masks, nerfstudio cameras on a circle,
metrics, traits, run times and test-view renders. ``stages`` picks which parts exist, so reports of
partial workspaces can be tested.

Usage:
    ws = make_synthetic_workspace("/tmp/ws_demo", n_gaussians=5000)
    (ws / "export" / "splat.ply").is_file()
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from plantsplat.io import write_image_atomic, write_json_atomic
from plantsplat.workspace import IMAGE_PATTERN, Workspace

ALL_STAGES = ("frames", "segment", "poses", "train", "export", "metrics", "traits", "run")


def synthetic_gaussians(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A plant-like set of ``n`` Gaussians in cm, z up: pot, stem, leaves, fruit, and a 10 cm cube.

    Returns Inria-PLY fields: ``means [N,3]``, ``log_scales [N,3]``, ``quats [N,4]`` (wxyz),
    ``f_dc [N,3]``, ``opacity [N]`` (logits) and ``part [N]`` (0 pot, 1 stem, 2 leaf, 3 fruit, 4 cube).
    """
    rng = np.random.default_rng(seed)
    fractions = {"pot": 0.15, "stem": 0.05, "leaf": 0.6, "fruit": 0.05, "cube": 0.15}
    counts = {k: int(round(v * n)) for k, v in fractions.items()}
    counts["leaf"] += n - sum(counts.values())
    parts, means, colours = [], [], []

    # pot: cylinder wall, radius 6 cm, z 0..10, brown
    m = counts["pot"]
    a = rng.uniform(0, 2 * np.pi, m)
    means.append(np.stack([6 * np.cos(a), 6 * np.sin(a), rng.uniform(0, 10, m)], 1))
    colours.append(np.tile([0.45, 0.28, 0.15], (m, 1)))
    parts.append(np.full(m, 0))
    # stem: from the pot's soil (z=10) up to z=18
    m = counts["stem"]
    t = rng.uniform(0, 1, m)
    means.append(np.stack([rng.normal(0, 0.3, m), rng.normal(0, 0.3, m), 10 + 8 * t], 1))
    colours.append(np.tile([0.35, 0.55, 0.2], (m, 1)))
    parts.append(np.full(m, 1))
    # leaves: 7 elliptical blades around the crown, tilted upward
    m = counts["leaf"]
    leaf = rng.integers(0, 7, m)
    ang = leaf * (2 * np.pi / 7) + 0.3
    u, v = rng.uniform(0, 1, m), rng.uniform(-1, 1, m)
    r = 3 + 11 * u  # distance from the stem
    half_width = 3.5 * np.sin(np.pi * u)
    w = v * half_width
    z = 16 + 6 * u - 3 * u**2 + rng.normal(0, 0.15, m)
    means.append(np.stack([r * np.cos(ang) - w * np.sin(ang), r * np.sin(ang) + w * np.cos(ang), z], 1))
    colours.append(np.stack([0.15 + 0.1 * u, 0.45 + 0.2 * u, 0.12 + 0.05 * v], 1))
    parts.append(np.full(m, 2))
    # fruit: 3 red berries hanging below the leaves
    m = counts["fruit"]
    berry = rng.integers(0, 3, m)
    centre = np.stack([9 * np.cos(berry * 2.1), 9 * np.sin(berry * 2.1), np.full(m, 13.0)], 1)
    d = rng.normal(0, 1, (m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means.append(centre + 1.5 * d)
    colours.append(np.tile([0.85, 0.1, 0.1], (m, 1)))
    parts.append(np.full(m, 3))
    # cube: 10 cm, standing on the ground beside the pot, light grey faces
    m = counts["cube"]
    face = rng.integers(0, 6, m)
    p = rng.uniform(0, 10, (m, 3))
    axis, side = face // 2, (face % 2) * 10.0
    p[np.arange(m), axis] = side
    means.append(p + np.array([15.0, -5.0, 0.0]))
    colours.append(np.tile([0.85, 0.85, 0.82], (m, 1)))
    parts.append(np.full(m, 4))

    means_a = np.concatenate(means).astype(np.float32)  # [N, 3]
    rgb = np.clip(np.concatenate(colours) + rng.normal(0, 0.03, (n, 3)), 0.02, 0.98)
    q = rng.normal(0, 1, (n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {
        "means": means_a,
        "log_scales": np.log(rng.uniform(0.15, 0.45, (n, 3))).astype(np.float32),
        "quats": q.astype(np.float32),
        "f_dc": ((rgb - 0.5) / 0.28209479177387814).astype(np.float32),
        "opacity": rng.uniform(1.0, 4.0, n).astype(np.float32),
        "part": np.concatenate(parts),
    }


def write_inria_ply(path: str | os.PathLike, g: dict[str, np.ndarray], sh_rest: int = 45) -> None:
    """Write Gaussians as an Inria-layout 3DGS PLY (degree-3 SH rest coefficients set to 0)."""
    from plantsplat.ply import write_splat

    n = len(g["means"])
    write_splat(path, g["means"], g["log_scales"], g["quats"], g["opacity"], np.asarray(g["f_dc"])[:, None, :],
                np.zeros((n, sh_rest // 3, 3), np.float32))


def orbit_cameras(n: int, radius: float = 45.0, height: float = 30.0, target=(0.0, 0.0, 12.0)) -> list[np.ndarray]:
    """``n`` camera-to-world matrices [4, 4] (OpenGL axes) on a circle, looking at ``target``."""
    mats = []
    t = np.asarray(target, dtype=np.float64)
    for i in range(n):
        a = 2 * math.pi * i / n
        c = np.array([radius * math.cos(a), radius * math.sin(a), height])
        back = c - t
        back /= np.linalg.norm(back)  # camera +z (OpenGL looks along -z)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, c
        mats.append(m)
    return mats


def make_synthetic_workspace(
    root: str | os.PathLike,
    n_gaussians: int = 20_000,
    n_frames: int = 12,
    image_size: tuple[int, int] = (160, 120),
    stages: tuple[str, ...] = ALL_STAGES,
    seed: int = 0,
) -> Path:
    """Write a synthetic workspace with the parts named in ``stages`` (see :data:`ALL_STAGES`)."""
    ws = Workspace(root)
    ws.root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    w, h = image_size
    names = [IMAGE_PATTERN.format(i) for i in range(n_frames)]
    yy, xx = np.mgrid[0:h, 0:w]

    def frame(i: int) -> tuple[np.ndarray, np.ndarray]:
        cx = w * (0.45 + 0.1 * math.sin(i))
        mask = (((xx - cx) / (0.22 * w)) ** 2 + ((yy - 0.55 * h) / (0.35 * h)) ** 2) < 1.0  # [H, W]
        img = np.empty((h, w, 3), np.uint8)
        img[..., 0] = 90 + 60 * yy / h
        img[..., 1] = 80 + 40 * xx / w
        img[..., 2] = 70
        img[mask] = (40, 140, 50)
        img = np.clip(img + rng.integers(-12, 12, img.shape), 0, 255).astype(np.uint8)
        return img, (mask * 255).astype(np.uint8)

    if "frames" in stages:
        for i, name in enumerate(names):
            write_image_atomic(ws.images_dir / name, frame(i)[0])
        write_json_atomic(ws.frames_json, {"source": "synthetic", "frames": [
            {"image": n, "source_index": 10 * i} for i, n in enumerate(names)]})
    if "segment" in stages:
        for i, name in enumerate(names):
            write_image_atomic(ws.masks_dir / name, frame(i)[1])
        write_image_atomic(ws.masks_preview_png, frame(0)[0])  # stand-ins: the report shows the figures it finds
        write_image_atomic(ws.segment_decision_png, frame(1)[0])
        write_json_atomic(ws.segment_json, {"backend": "3d", "confidence": {"mean": 0.91, "min": 0.83,
                                                                             "least_sure": names[0]}})
    if "poses" in stages:
        f = 0.9 * w
        frames = [{"file_path": f"images/{n}", "transform_matrix": m.tolist()}
                  for n, m in zip(names, orbit_cameras(n_frames))]
        write_json_atomic(ws.transforms_json, {"camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": w / 2,
                                               "cy": h / 2, "w": w, "h": h, "frames": frames})
    from plantsplat.ply import write_point_cloud

    g = synthetic_gaussians(n_gaussians, seed)
    if "export" in stages:
        write_inria_ply(ws.splat_ply, g)
        rgb = np.clip(np.round((0.5 + 0.28209479177387814 * g["f_dc"]) * 255), 0, 255).astype(np.uint8)
        write_point_cloud(ws.points_ply, g["means"], rgb)
    if "train" in stages:
        for i in range(0, n_frames, max(1, n_frames // 3)):
            img, _ = frame(i)
            noisy = np.clip(img.astype(int) + rng.integers(-20, 20, img.shape), 0, 255).astype(np.uint8)
            stem = Path(names[i]).stem
            write_image_atomic(ws.train_dir / "renders" / f"{stem}_render.png", noisy)
            write_image_atomic(ws.train_dir / "renders" / f"{stem}_gt.png", img)
    if "metrics" in stages:
        write_json_atomic(ws.metrics_json, {
            "psnr": 27.31, "ssim": 0.912, "lpips": 0.083, "num_test_views": 4,
            "per_view": {"frame_00000.png": {"psnr": 27.0, "ssim": 0.91}, "frame_00004.png": {"psnr": 27.6, "ssim": 0.914}},
        })
    if "traits" in stages:
        plant = g["means"][np.isin(g["part"], [1, 2, 3])]
        from plantsplat.traitdefs import geometric_traits

        traits = geometric_traits(plant)
        traits["fruit_count"] = 3
        write_json_atomic(ws.traits_json, {**traits, "scale_cm_per_unit": 1.0, "n_points": int(len(plant))})
        _traits_figure(ws.traits_png, plant)
    if "run" in stages:
        write_json_atomic(ws.run_json, {"stages": {
            "frames": {"seconds": 4.2, "peak_rss_mb": 310.0}, "segment": {"seconds": 21.5, "peak_rss_mb": 820.0},
            "poses": {"seconds": 35.1, "peak_rss_mb": 640.0}, "train": {"seconds": 412.0, "peak_rss_mb": 2100.0},
            "export": {"seconds": 1.3, "peak_rss_mb": 500.0}, "traits": {"seconds": 2.8, "peak_rss_mb": 450.0}}})
    return ws.root


def _traits_figure(path: Path, plant: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from plantsplat.io import atomic_path

    fig, ax = plt.subplots(1, 2, figsize=(6, 3), dpi=80)
    ax[0].scatter(plant[:, 0], plant[:, 1], s=1, c="g")
    ax[0].set_title("top view")
    ax[1].scatter(plant[:, 0], plant[:, 2], s=1, c="g")
    ax[1].set_title("side view")
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)

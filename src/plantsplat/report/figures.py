"""Figures for the plant report: frame contact sheet with mask overlays, camera path, render pairs.

Usage:
    sheet, shown, with_mask = frames_contact_sheet(Workspace("ws/plant_01"), max_frames=24)
    sheet.shape[2], shown
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.segment.preview import contact_sheet as sheet_of
from plantsplat.workspace import Workspace


def pick_evenly(items: list, k: int) -> list:
    """``k`` items spread evenly over ``items`` (all of them when there are fewer)."""
    if len(items) <= k:
        return list(items)
    idx = np.round(np.linspace(0, len(items) - 1, k)).astype(int)
    return [items[i] for i in idx]


def frames_contact_sheet(ws: Workspace, max_frames: int = 24, tile_height: int = 320, columns: int = 6
                  ) -> tuple[np.ndarray, int, int]:
    """Grid of evenly spread frames, with the mask overlaid where ``masks/`` has the frame
    (:func:`plantsplat.segment.preview.contact_sheet`).

    Returns ``(sheet [H, W, 3] uint8, frames shown, frames with a mask)``.
    """
    names = ws.image_names()
    if not names:
        raise PlantsplatError(f"{ws.images_dir}: no frames")
    chosen = pick_evenly(names, max_frames)
    masks = [ws.masks_dir / n if (ws.masks_dir / n).is_file() else None for n in chosen]
    sheet = sheet_of([ws.images_dir / n for n in chosen], masks, labels=[Path(n).stem.replace("frame_", "#") for n in chosen],
                     max_tiles=len(chosen), tile_height=tile_height, columns=columns)
    return sheet, len(chosen), sum(m is not None for m in masks)


def read_cameras(path: Path) -> tuple[np.ndarray, list[str]]:
    """Camera-to-world matrices [N, 4, 4] and file names from a nerfstudio ``transforms.json``."""
    try:
        data = json.loads(path.read_text())
        frames = data["frames"]
        mats = np.array([f["transform_matrix"] for f in frames], dtype=np.float64)
        names = [str(f.get("file_path", "")) for f in frames]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise PlantsplatError(f"{path}: not a readable nerfstudio transforms.json ({type(exc).__name__}: {exc}); "
                              "re-run `plantsplat poses`") from exc
    if mats.ndim != 3 or mats.shape[1:] not in {(4, 4), (3, 4)} or len(mats) == 0:
        raise PlantsplatError(f"{path}: transform_matrix entries are not 4x4 matrices; re-run `plantsplat poses`")
    if mats.shape[1] == 3:
        mats = np.concatenate([mats, np.tile([[[0, 0, 0, 1.0]]], (len(mats), 1, 1))], axis=1)
    return mats, names


def camera_path_png(c2w: np.ndarray, scene_points: np.ndarray | None = None) -> bytes:
    """A two-panel figure (3D view and top view) of the camera centres, viewing directions and path.

    ``c2w`` [N, 4, 4] camera-to-world in OpenGL axes (the camera looks along its -z), world z up, cm;
    ``scene_points`` [M, 3] (optional) are drawn as a grey cloud for reference.
    """
    matplotlib.use("Agg")
    centres = c2w[:, :3, 3]  # [N, 3]
    look = -c2w[:, :3, 2]  # [N, 3] viewing directions
    span = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 1.0
    arrow = 0.12 * max(span, 1e-6)
    colours = plt.cm.viridis(np.linspace(0, 1, len(centres)))

    fig = plt.figure(figsize=(11, 4.8), dpi=90)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    if scene_points is not None and len(scene_points):
        sp = scene_points[np.random.default_rng(0).choice(len(scene_points), min(3000, len(scene_points)), replace=False)]
        ax3.scatter(sp[:, 0], sp[:, 1], sp[:, 2], s=0.5, c="0.55", alpha=0.5)
        ax2.scatter(sp[:, 0], sp[:, 1], s=0.5, c="0.55", alpha=0.5)
    ax3.plot(centres[:, 0], centres[:, 1], centres[:, 2], "-", c="0.6", lw=0.8)
    ax3.scatter(centres[:, 0], centres[:, 1], centres[:, 2], c=colours, s=12)
    ax3.quiver(centres[:, 0], centres[:, 1], centres[:, 2], look[:, 0], look[:, 1], look[:, 2],
               length=arrow, color=colours, linewidth=0.8)
    ax3.set_xlabel("x (cm)")
    ax3.set_ylabel("y (cm)")
    ax3.set_zlabel("z (cm)")
    lo, hi = centres.min(0), centres.max(0)
    if scene_points is not None and len(scene_points):
        lo, hi = np.minimum(lo, scene_points.min(0)), np.maximum(hi, scene_points.max(0))
    mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    ax3.set_xlim(mid[0] - half, mid[0] + half)
    ax3.set_ylim(mid[1] - half, mid[1] + half)
    ax3.set_zlim(mid[2] - half, mid[2] + half)
    ax3.set_title("cameras (colour = frame order)")
    ax2.plot(centres[:, 0], centres[:, 1], "-", c="0.6", lw=0.8)
    ax2.scatter(centres[:, 0], centres[:, 1], c=colours, s=14, zorder=3)
    ax2.quiver(centres[:, 0], centres[:, 1], look[:, 0], look[:, 1], color=colours, angles="xy",
               scale_units="xy", scale=1.0 / arrow, width=0.003, zorder=2)
    ax2.plot([0], [0], "+", c="k", ms=10)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel("x (cm)")
    ax2.set_ylabel("y (cm)")
    ax2.set_title("top view (+ = world origin)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def render_pairs(renders_dir: Path) -> list[tuple[str, Path, Path]]:
    """``(name, render, ground truth)`` for every ``<name>_render.png`` with a ``<name>_gt.png`` beside it."""
    pairs = []
    for r in sorted(renders_dir.glob("*_render.png")):
        name = r.name[: -len("_render.png")]
        gt = renders_dir / f"{name}_gt.png"
        if gt.is_file():
            pairs.append((name, r, gt))
    return pairs



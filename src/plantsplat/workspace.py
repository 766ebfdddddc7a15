"""The workspace: one folder per plant, holding every stage's inputs and outputs.

Layout (every stage reads and writes only these paths; see the README's "Outputs")::

    WS/
      images/frame_00000.png      RGB frames chosen from the video               (frames)
      frames.json                 source video/folder, source frame index per image (frames)
      markers.json                the cube's marker corners in every frame     (poses)
      sparse/0/                   calibrated COLMAP model, binary (cm, z up)    (poses)
      sparse_text/0/              the same model as text                        (poses)
      transforms.json             nerfstudio cameras (OpenGL axes, cm, z up)    (poses)
      poses.json                  registration and calibration report           (poses)
      sparse_points.ply           SfM points (cm, z up)                          (poses)
      masks/frame_00000.png       uint8 mask, 255 = plant or cube               (segment)
      rgba/frame_00000.png        RGBA image, alpha = mask                      (segment)
      segment.json, masks_preview.png, segment_decision.png                     (segment)
      train/                      split.json, checkpoints, config               (train)
      export/splat.ply            Inria-layout 3DGS PLY                          (export)
      export/points.ply           opacity-filtered centres with colours         (export)
      metrics.json                image metrics on test views                   (train/evaluate)
      traits.json, traits.csv, traits.png                                       (traits)
      run.json                    per-stage times, memory, versions, config     (run)
      report.html                                                               (report)

Example:
    >>> ws = Workspace("ws/plant_01")
    >>> ws.images_dir
    PosixPath('ws/plant_01/images')
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from plantsplat.errors import PlantsplatError

IMAGE_PATTERN = "frame_{:05d}.png"


@dataclass(frozen=True)
class Workspace:
    root: Path

    def __init__(self, root: str | os.PathLike, must_exist: bool = False):
        object.__setattr__(self, "root", Path(root))
        if must_exist and not self.root.is_dir():
            what = "is not a folder" if self.root.exists() else "no such folder"
            raise PlantsplatError(f"{self.root}: {what}; give the workspace made by `plantsplat frames` or `plantsplat run`",
                                  exit_code=2)

    # frames
    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @property
    def frames_json(self) -> Path:
        return self.root / "frames.json"

    # segment
    @property
    def masks_dir(self) -> Path:
        return self.root / "masks"

    @property
    def rgba_dir(self) -> Path:
        return self.root / "rgba"

    @property
    def segment_json(self) -> Path:
        return self.root / "segment.json"

    @property
    def masks_preview_png(self) -> Path:
        """The segment stage's contact sheet of masks, least sure frames first."""
        return self.root / "masks_preview.png"

    @property
    def segment_decision_png(self) -> Path:
        """The segment stage's figure of its 3D decision (:mod:`plantsplat.segment.decision_figure`)."""
        return self.root / "segment_decision.png"

    # poses
    @property
    def markers_json(self) -> Path:
        return self.root / "markers.json"

    @property
    def sparse_dir(self) -> Path:
        return self.root / "sparse" / "0"

    @property
    def sparse_text_dir(self) -> Path:
        return self.root / "sparse_text" / "0"

    @property
    def transforms_json(self) -> Path:
        return self.root / "transforms.json"

    @property
    def poses_json(self) -> Path:
        return self.root / "poses.json"

    @property
    def sparse_points_ply(self) -> Path:
        return self.root / "sparse_points.ply"

    # train / export / evaluate
    @property
    def train_dir(self) -> Path:
        return self.root / "train"

    @property
    def export_dir(self) -> Path:
        return self.root / "export"

    @property
    def splat_ply(self) -> Path:
        return self.export_dir / "splat.ply"

    @property
    def points_ply(self) -> Path:
        return self.export_dir / "points.ply"

    @property
    def metrics_json(self) -> Path:
        return self.root / "metrics.json"

    # traits / run / report
    @property
    def traits_json(self) -> Path:
        return self.root / "traits.json"

    @property
    def traits_csv(self) -> Path:
        return self.root / "traits.csv"

    @property
    def traits_png(self) -> Path:
        return self.root / "traits.png"

    @property
    def plant_ply(self) -> Path:
        """The Gaussians of the plant alone, as the traits stage found it (Inria 3DGS PLY)."""
        return self.root / "plant.ply"

    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def report_html(self) -> Path:
        return self.root / "report.html"

    def image_names(self) -> list[str]:
        """Sorted file names in ``images/``."""
        if not self.images_dir.is_dir():
            return []
        return sorted(p.name for p in self.images_dir.iterdir() if p.suffix.lower() in {".png", ".jpg", ".jpeg"})

    def require(self, path: Path, stage: str) -> Path:
        """Raise a clear error when an input written by an earlier ``stage`` is missing."""
        if not path.exists():
            raise PlantsplatError(
                f"{path}: missing; run `plantsplat {stage} {self.root}` first"
            )
        return path


def prepare_output_dir(path: str | os.PathLike, force: bool = False) -> Path:
    """Create ``path`` for a new output; refuse a non-empty existing folder unless ``force``.

    ``force`` never deletes anything: files are overwritten one by one as they are rewritten.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise PlantsplatError(f"{path}: exists and is not a folder; choose another --out", exit_code=2)
    if path.is_dir() and any(path.iterdir()) and not force:
        raise PlantsplatError(
            f"{path}: folder exists and is not empty; choose another --out or pass --force", exit_code=2
        )
    path.mkdir(parents=True, exist_ok=True)
    return path

"""The export stage's settings: :class:`ExportConfig`, each option a documented field.

Example:
    >>> ExportConfig().min_opacity, ExportConfig(train_dir=None).train_dir
    (0.1, None)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass
class ExportConfig:
    """Options of ``plantsplat export``."""

    min_opacity: float = 0.1
    """Centres with a lower opacity are left out of points.ply (the paper's culling threshold)."""
    train_dir: Path | None = None
    """Folder of the trained model (default WS/train)."""

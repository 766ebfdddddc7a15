"""One module per CLI sub-command.

Each module in this package defines ``COMMAND = Command(...)``: a name, a config dataclass (its
fields, documented by the docstring under each, become the command-line options via tyro) and a
function that runs it. Command modules must import only light modules at top level (no torch,
Open3D or pycolmap) so that ``plantsplat --help`` stays instant; heavy imports go inside ``run``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Command:
    name: str
    """Sub-command name, e.g. ``synth``."""
    config: type
    """Config dataclass parsed from the command line."""
    run: Callable[[Any], int | None]
    """Runs the command; returns an exit code (None = 0)."""
    help: str
    """One-line description shown by ``plantsplat --help``."""
    order: int = 50
    """Position in the help listing (pipeline order)."""

"""Logging and progress bars shared by every stage (rich).

Use :func:`get_logger` for messages and :func:`progress` for any loop that takes more than a second::

    from plantsplat.log import get_logger, progress
    log = get_logger(__name__)
    for frame in progress(frames, "rendering"):
        ...
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from typing import TypeVar

from rich.console import Console
from rich.logging import RichHandler
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

T = TypeVar("T")

console = Console(stderr=True)
_configured = False


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    """Configure the ``plantsplat`` logger once (rich handler on stderr)."""
    global _configured
    level = logging.DEBUG if verbose else (logging.WARNING if quiet else logging.INFO)
    root = logging.getLogger("plantsplat")
    root.setLevel(level)
    if not _configured:
        handler = RichHandler(console=console, show_path=False, show_time=False, markup=False)
        handler.setFormatter(logging.Formatter("%(message)s"))
        root.addHandler(handler)
        root.propagate = False
        _configured = True


def get_logger(name: str) -> logging.Logger:
    """Return a child of the ``plantsplat`` logger."""
    if not name.startswith("plantsplat"):
        name = f"plantsplat.{name}"
    return logging.getLogger(name)


def progress_enabled() -> bool:
    """Progress bars are shown on a terminal, hidden under CI or when PLANTSPLAT_NO_PROGRESS is set."""
    if os.environ.get("PLANTSPLAT_NO_PROGRESS"):
        return False
    return console.is_terminal


def make_progress(transient: bool = False) -> Progress:
    """A rich Progress with count, bar, elapsed and remaining time (disabled when not a terminal)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        transient=transient,
        disable=not progress_enabled(),
    )


def progress(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate over ``items`` with a progress bar; logs a start and end line when bars are hidden."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    log = get_logger("progress")
    if not progress_enabled():
        log.info("%s (%s items)", description, total if total is not None else "?")
    with make_progress() as bar:
        task = bar.add_task(description, total=total, info="")
        for item in items:
            yield item
            bar.advance(task)


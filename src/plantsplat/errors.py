"""User-facing errors.

Anything a user can cause (bad input, a missing file, a failed stage) raises :class:`PlantsplatError`
with a one-line message that names the file and says what to do. The CLI prints it as
``error: <message>`` and exits with ``exit_code``; no traceback reaches the user.
"""

from __future__ import annotations


class PlantsplatError(Exception):
    """A clear, one-line, user-facing error.

    Example:
        >>> raise PlantsplatError("video.mp4: no frames could be decoded; re-export the video as H.264")
    """

    exit_code: int = 1

    def __init__(self, message: str, exit_code: int | None = None):
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = exit_code


class UsageError(PlantsplatError):
    """Impossible arguments (sizes, counts, paths): exit code 2, like argparse."""

    exit_code = 2

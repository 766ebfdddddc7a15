"""User-facing errors.

Anything a user can cause (bad input, a missing file, a failed stage) raises :class:`PlantsplatError`
with a one-line message that names the file and says what to do. The CLI prints it as
``error: <message>`` and exits with ``exit_code``; no traceback reaches the user.
"""

from __future__ import annotations

EXIT_POSES_FAILED = 3
"""The poses stage could not register the capture, or its camera model failed its checks (nothing written)."""
EXIT_RESULT_FAILED = 4
"""The traits were measured but a check of a stage or of the measurement failed: every file is written, and
``traits.json`` says ``quality: failed`` with the checks that decided it."""


class PlantsplatError(Exception):
    """A clear, one-line, user-facing error.

    Example:
        >>> err = PlantsplatError("video.mp4: no frames could be decoded; re-export the video as H.264")
        >>> err.exit_code, PlantsplatError("x", exit_code=EXIT_POSES_FAILED).exit_code
        (1, 3)
    """

    exit_code: int = 1

    def __init__(self, message: str, exit_code: int | None = None):
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = exit_code


class UsageError(PlantsplatError):
    """Impossible arguments (sizes, counts, paths): exit code 2, like argparse."""

    exit_code = 2

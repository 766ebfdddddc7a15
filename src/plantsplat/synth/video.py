"""H.264 video writing with PyAV (libx264, yuv420p), atomically.

Usage:
    with VideoWriter("out/video.mp4", 540, 960, fps=24) as vw:
        vw.write(rgb_uint8)                                      # [960, 540, 3]
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from plantsplat.io import atomic_path


class VideoWriter:
    """Encode RGB uint8 frames to an H.264 mp4; the file appears at ``path`` only when closed cleanly."""

    def __init__(self, path: str | Path, width: int, height: int, fps: int = 24, crf: int = 18,
                 preset: str = "veryfast"):
        import av

        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(path))
        self.container = av.open(str(self._tmp), mode="w", format="mp4")
        self.stream = self.container.add_stream("libx264", rate=fps)
        self.stream.width, self.stream.height = int(width), int(height)
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(crf), "preset": preset}
        self.settings = dict(codec="libx264", pix_fmt="yuv420p", crf=crf, preset=preset, fps=fps)
        self.n = 0

    def write(self, rgb: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)
        self.n += 1

    def close(self, ok: bool = True) -> None:
        try:
            if ok:
                for packet in self.stream.encode():
                    self.container.mux(packet)
            self.container.close()
        finally:
            if ok:
                self._stack.close()
            else:
                self._stack.__exit__(RuntimeError, RuntimeError("aborted"), None)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(ok=exc_type is None)

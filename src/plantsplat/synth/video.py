"""H.264 video writing with PyAV (libx264, yuv420p), atomically.

Usage:
    with VideoWriter("out/video.mp4", 540, 960, fps=24) as vw:
        vw.write(rgb_uint8)                                      # [960, 540, 3]
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from pathlib import Path

import av
import numpy as np

from plantsplat.io import atomic_path, read_image


class VideoWriter:
    """Encode RGB uint8 frames to an H.264 mp4; the file appears at ``path`` only when closed cleanly."""

    def __init__(self, path: str | Path, width: int, height: int, fps: int = 24, crf: int = 18,
                 preset: str = "veryfast"):
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
        frame = av.VideoFrame.from_ndarray(np.array(rgb, dtype=np.uint8, order="C", copy=True), format="rgb24")
        frame.pts = self.n  # timestamps from the frame count, not left to the library
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


def encode_frames(frames: list[Path], path: Path, width: int, height: int, fps: int, crf: int) -> dict:
    """Encode the image files ``frames`` (in order) to ``path`` in a fresh Python process; returns the settings.

    In the process that rendered the frames (OpenGL through llvmpipe), libx264 encoded the same frames to a
    different video from run to run (51 of 120 frames, up to 40 grey levels; the cause was not found); a process
    of its own encodes them the same every time."""
    job = json.dumps({"frames": [str(f) for f in frames], "path": str(path), "width": width, "height": height,
                      "fps": fps, "crf": crf})
    done = subprocess.run([sys.executable, "-m", "plantsplat.synth.video"], input=job, text=True, capture_output=True)
    if done.returncode != 0:
        raise RuntimeError(f"{path}: encoding the video failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout)


def _encode_job() -> None:
    job = json.loads(sys.stdin.read())
    with VideoWriter(job["path"], job["width"], job["height"], job["fps"], crf=job["crf"]) as vw:
        for f in job["frames"]:
            vw.write(read_image(f))
    print(json.dumps(vw.settings))


if __name__ == "__main__":
    _encode_job()

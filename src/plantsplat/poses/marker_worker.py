"""The marker detection process of :func:`plantsplat.poses.stage.start_markers`: ``python -m
plantsplat.poses.marker_worker IMAGES NAMES CUBE OUT``, where ``IMAGES`` is the frames' folder, ``NAMES`` a file of
frame names (one per line), ``CUBE`` the cube as JSON (:meth:`~plantsplat.cube.CubeSpec.record`) and ``OUT`` the
file it writes the :class:`~plantsplat.markers.Markers` into (pickled, so the corners are exactly those of a
detection in the stage's own process), with the seconds the detection took. A frame it cannot read ends it with that
frame's one-line error and its exit code in ``OUT.error.json``.

It runs at the lowest priority (nice 19), beside structure from motion: it takes the cycles that the stage's
one-thread steps (learning the vocabulary, mapping's end, the bundle adjustments) leave idle, and hardly any from
its many-thread steps. Ctrl-C is left to the stage, which stops it."""

from __future__ import annotations

import json
import os
import pickle
import sys
import time
from pathlib import Path

from plantsplat.cube import CubeSpec
from plantsplat.errors import PlantsplatError
from plantsplat.io import write_json_atomic
from plantsplat.markers import detect_frames
from plantsplat.workers import worker_start


def error_file(out: Path) -> Path:
    """Where the process leaves a frame's error instead of ``out``."""
    return out.with_name(out.name + ".error.json")


def main(argv: list[str]) -> int:
    worker_start(lowest_priority=True)
    images, names, out = Path(argv[0]), Path(argv[1]).read_text().splitlines(), Path(argv[3])
    cube = CubeSpec.from_record(json.loads(argv[2]))
    t0 = time.perf_counter()
    try:
        markers = detect_frames(images, names, cube)
    except PlantsplatError as exc:
        write_json_atomic(error_file(out), {"message": str(exc), "exit_code": exc.exit_code})
        return 1
    part = out.with_name(out.name + ".partial")
    with open(part, "wb") as f:
        pickle.dump({"markers": markers, "seconds": time.perf_counter() - t0}, f)
    os.replace(part, out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The global mapping process of :func:`plantsplat.poses.sfm.start_global_mapping`: ``python -m
plantsplat.poses.map_worker DB IMAGES OUT OPTIONS``, where ``DB`` is its own copy of the COLMAP database, ``IMAGES``
the frames, ``OUT`` its folder and ``OPTIONS`` the :class:`~plantsplat.poses.sfm.SfmConfig` as JSON. It runs
:func:`~plantsplat.poses.sfm.global_then_incremental` and writes the models, largest first, into ``OUT/models``.
Ctrl-C is left to the stage, which stops it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from plantsplat.poses.sfm import MAPPED_DIR, SfmConfig, global_then_incremental, write_models
from plantsplat.workers import worker_start


def main(argv: list[str]) -> int:
    worker_start()
    db, images, out = Path(argv[0]), Path(argv[1]), Path(argv[2])
    opts = SfmConfig(**json.loads(argv[3]))
    write_models(global_then_incremental(db, images, out / "run", opts), out / MAPPED_DIR, opts.verbose)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""One matching process of :func:`plantsplat.poses.sfm.match_pairs`: ``python -m plantsplat.poses.match_worker DB PAIRS
OPTIONS``, where ``DB`` is its own copy of the COLMAP database, ``PAIRS`` the file of image-name pairs to match (one
pair per line) and ``OPTIONS`` the :class:`~plantsplat.poses.sfm.SfmConfig` as JSON. A separate interpreter rather
than :mod:`multiprocessing`, so that no user's main module is imported again in the worker. Ctrl-C is left to the
stage, which stops the workers."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from plantsplat.poses.sfm import SfmConfig, match_pair_list
from plantsplat.workers import worker_start


def main(argv: list[str]) -> int:
    worker_start()
    # stderr is this worker's log.txt: COLMAP's errors (a failed check before an abort) are what the stage quotes
    match_pair_list(Path(argv[0]), Path(argv[1]), SfmConfig(**json.loads(argv[2])), keep_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

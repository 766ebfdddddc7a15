"""One matching process of :func:`plantsplat.poses.sfm.match_pairs`: ``python -m plantsplat.poses.match_worker DB PAIRS
OPTIONS``, where ``DB`` is its own copy of the COLMAP database, ``PAIRS`` the file of image-name pairs to match (one
pair per line) and ``OPTIONS`` the :class:`~plantsplat.poses.sfm.SfmConfig` as JSON. A separate interpreter rather
than :mod:`multiprocessing`, so that no user's main module is imported again in the worker. Ctrl-C is left to the
stage, which stops the workers."""

from __future__ import annotations

import ctypes
import json
import os
import signal
import sys
from pathlib import Path

from plantsplat.poses.sfm import PARENT_ENV, SfmConfig, match_pair_list

PR_SET_PDEATHSIG = 1
"""Linux's prctl option: the signal this process gets when the thread that started it ends."""


def die_with_parent() -> None:
    """End this process when the stage that started it dies, however it dies: a SIGKILL or the out-of-memory killer
    gives the stage no chance to stop its workers, which would go on matching, orphaned, for minutes (Linux: the
    kernel sends SIGKILL; elsewhere nothing changes). A stage already gone (``PARENT_ENV`` no longer our parent)
    ends it at once."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    parent = int(os.environ.get(PARENT_ENV, "0"))
    if parent and os.getppid() != parent:
        sys.exit(1)


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent()
    match_pair_list(Path(argv[0]), Path(argv[1]), SfmConfig(**json.loads(argv[2])))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

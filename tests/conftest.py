"""Shared pytest fixtures.

- ``synth_capture``: a factory that renders a small synthetic capture with ``plantsplat synth`` once per
  session and argument set, e.g. ``cap = synth_capture(seed=0, frames=36, width=180, height=320)``
  returns the capture folder (``video.mp4``, ``frames/``, ``masks/``, ``plant_gt.ply``,
  ``scene_gt.ply``, ``ground_truth.json``). Extra keyword arguments go to ``SynthConfig`` (e.g.
  ``clean=True``). Treat the folder as read-only: other tests share it.
- ``datasets_dir``: the shared real/virtual datasets folder (``PLANTSPLAT_DATASETS`` overrides
  ``<repo>/../shared/datasets``), or a skip with a message when it is absent.

Markers: ``cuda`` tests are skipped where CUDA is absent; ``slow`` marks whole-pipeline runs (a quick
pass: ``pytest -m "not slow"``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ["PLANTSPLAT_NO_PROGRESS"] = "1"


@pytest.fixture(autouse=True)
def no_doctest_result_in_builtins():
    """Each test starts without the ``_`` a doctest's last expression leaves in ``builtins`` (doctest runs examples as
    an interactive session does). tyro hashes every builtin when the CLI first parses its options, and a tuple of
    lists there (``widths.py``'s example prints one) failed it in whichever CLI test came after that doctest. A
    callable ``_`` (gettext's, installed by a library) is left alone."""
    import builtins

    if hasattr(builtins, "_") and not callable(builtins._):
        del builtins._
    yield


def pytest_collection_modifyitems(config, items):
    """Skip ``cuda`` tests cleanly on machines without CUDA."""
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA (none on this machine)")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def synth_capture(tmp_path_factory):
    """``make(seed=0, frames=36, width=180, height=320, **cfg) -> Path``, cached per argument set."""
    from plantsplat.synth import SynthConfig, generate

    cache: dict[tuple, Path] = {}

    def make(seed: int = 0, frames: int = 36, width: int = 180, height: int = 320, **kw) -> Path:
        key = (seed, frames, width, height, tuple(sorted(kw.items())))
        if key not in cache:
            name = f"synth_s{seed}_f{frames}_{width}x{height}" + "".join(f"_{k}{v}" for k, v in sorted(kw.items()))
            out = tmp_path_factory.mktemp(name)
            generate(SynthConfig(out=out, seed=seed, frames=frames, width=width, height=height, force=True, **kw))
            cache[key] = out
        return cache[key]

    return make


@pytest.fixture
def interrupted_after():
    """``interrupted_after(real, n)``: a stand-in for a function (a ``write(path, data)``, a training step's
    ``render``) that raises KeyboardInterrupt (a Ctrl-C mid-stage) on its ``n``-th call and otherwise returns
    what ``real`` returns."""

    def make(real, n: int):
        calls = []

        def stand_in(*args, **kwargs):
            calls.append(args)
            if len(calls) == n:
                raise KeyboardInterrupt
            return real(*args, **kwargs)

        return stand_in

    return make


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """The shared datasets folder, or skip when it is not there."""
    env = os.environ.get("PLANTSPLAT_DATASETS")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "datasets"
    if not path.is_dir():
        pytest.skip(f"datasets folder {path} not found (set PLANTSPLAT_DATASETS to run these tests)")
    return path

"""`plantsplat doctor`: what this machine can run (libraries, OpenGL, CUDA/gsplat, SAM-2, LPIPS)."""

from __future__ import annotations

import importlib
import json
import platform
from dataclasses import dataclass

from rich.table import Table

from plantsplat.commands import Command
from plantsplat.log import console


@dataclass
class DoctorCommand:
    """Check the installation: library versions, headless OpenGL, CUDA and gsplat, optional models."""

    json: bool = False
    """Print the findings as JSON instead of a table."""


def _check(name: str, fn):
    try:
        return name, True, str(fn())
    except Exception as exc:  # report, never crash: this command exists to diagnose failures
        return name, False, f"{type(exc).__name__}: {exc}".splitlines()[0][:160]


def collect() -> list[tuple[str, bool, str]]:
    """Return ``(component, ok, detail)`` rows describing this machine."""
    rows = [("python", True, platform.python_version())]
    for mod in ["numpy", "torch", "numba", "cv2", "av", "pycolmap", "open3d", "moderngl", "tyro"]:
        rows.append(_check(mod, _version(mod)))
    rows.append(_check("opengl (egl)", _opengl_renderer))
    rows.append(_check("cuda", _cuda_device))
    rows.append(_check("gsplat (optional)", _version("gsplat")))
    rows.append(_check("sam2 (optional)", _version("sam2")))
    rows.append(_check("ray (optional)", _version("ray")))
    return rows


def _version(mod: str):
    return lambda: getattr(importlib.import_module(mod), "__version__", "installed")


def _opengl_renderer() -> str:
    """The renderer of a headless (EGL) OpenGL context."""
    import moderngl  # deferred: a check, which reports a missing or broken moderngl as such

    ctx = moderngl.create_standalone_context(backend="egl")
    info = ctx.info["GL_RENDERER"]
    ctx.release()
    return info


def _cuda_device() -> str:
    """The name of the first CUDA device."""
    import torch  # deferred: torch is slow to load, and the CLI imports this module

    if not torch.cuda.is_available():
        raise RuntimeError("no CUDA device; the CPU backend will be used")
    return torch.cuda.get_device_name(0)


def run(cfg: DoctorCommand) -> int:
    rows = collect()
    if cfg.json:
        print(json.dumps([{"component": n, "ok": ok, "detail": d} for n, ok, d in rows], indent=2))
        return 0
    table = Table(title="plantsplat doctor")
    table.add_column("component")
    table.add_column("status")
    table.add_column("detail")
    for name, ok, detail in rows:
        table.add_row(name, "[green]ok[/]" if ok else "[yellow]missing[/]", detail)
    console.print(table)
    return 0


COMMAND = Command(name="doctor", config=DoctorCommand, run=run, help="Check what this machine can run.", order=99)

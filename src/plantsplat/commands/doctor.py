"""`plantsplat doctor`: what this machine can run (libraries, OpenGL, CUDA/gsplat, SAM-2, LPIPS)."""

from __future__ import annotations

from dataclasses import dataclass

from plantsplat.commands import Command


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
    import importlib
    import platform

    def version(mod: str):
        return lambda: getattr(importlib.import_module(mod), "__version__", "installed")

    rows = [("python", True, platform.python_version())]
    for mod in ["numpy", "torch", "numba", "cv2", "av", "pycolmap", "open3d", "moderngl", "tyro"]:
        rows.append(_check(mod, version(mod)))

    def gl():
        import moderngl

        ctx = moderngl.create_standalone_context(backend="egl")
        info = ctx.info["GL_RENDERER"]
        ctx.release()
        return info

    rows.append(_check("opengl (egl)", gl))

    def cuda():
        import torch

        if not torch.cuda.is_available():
            raise RuntimeError("no CUDA device; the CPU backend will be used")
        return torch.cuda.get_device_name(0)

    rows.append(_check("cuda", cuda))
    rows.append(_check("gsplat (optional)", version("gsplat")))
    rows.append(_check("sam2 (optional)", version("sam2")))
    rows.append(_check("ray (optional)", version("ray")))
    return rows


def run(cfg: DoctorCommand) -> int:
    rows = collect()
    if cfg.json:
        import json

        print(json.dumps([{"component": n, "ok": ok, "detail": d} for n, ok, d in rows], indent=2))
        return 0
    from rich.table import Table

    from plantsplat.log import console

    table = Table(title="plantsplat doctor")
    table.add_column("component")
    table.add_column("status")
    table.add_column("detail")
    for name, ok, detail in rows:
        table.add_row(name, "[green]ok[/]" if ok else "[yellow]missing[/]", detail)
    console.print(table)
    return 0


COMMAND = Command(name="doctor", config=DoctorCommand, run=run, help="Check what this machine can run.", order=99)

"""The package's shape: no import cycle between plantsplat's modules (imports inside functions count), no module
uses another module's private names, no module is over 600 lines (raster/ aside), and every stage package has the
same layout (config.py with its dataclass config, stage.py with run, inputs and outputs)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
MAX_LINES = 600
"""The longest module allowed outside raster/ (the reference rasterizer and its kernels)."""
STAGE_PACKAGES = ("frames", "poses", "segment", "train", "export", "traits")
"""Every stage: each is a package with the same layout (issue 44)."""


def _modules() -> dict[str, Path]:
    mods = {}
    for p in (SRC / "plantsplat").rglob("*.py"):
        parts = list(p.relative_to(SRC).with_suffix("").parts)
        mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return mods


def _imports(mods: dict[str, Path]):
    """``{module: {imported plantsplat module}}`` and every ``(module, imported name)`` that is private."""
    edges: dict[str, set[str]] = {m: set() for m in mods}
    private = []
    for m, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("plantsplat"):
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    edges[m].add(full if full in mods else node.module)
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        private.append((m, full))
            elif isinstance(node, ast.Import):
                edges[m].update(a.name for a in node.names if a.name in mods)
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                if isinstance(node.value, ast.Name) and node.value.id in _module_aliases(path):
                    private.append((m, f"{node.value.id}.{node.attr}"))
    return {m: {t for t in e if t in mods and t != m} for m, e in edges.items()}, private


def _module_aliases(path: Path) -> set[str]:
    """Names a module binds to other plantsplat modules (``from plantsplat.train import data as D`` -> D)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("plantsplat"):
            names.update(a.asname or a.name for a in node.names if (SRC / (node.module.replace(".",
                                                                                               "/")) / f"{a.name}.py").exists())
        elif isinstance(node, ast.Import):
            names.update((a.asname or a.name).split(".")[0] for a in node.names if a.name.startswith("plantsplat"))
    return names


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (a list of modules), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if t not in state and (found := visit(t)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_import_cycle():
    edges, _ = _imports(_modules())
    assert _cycle(edges) is None, " -> ".join(_cycle(edges))


def test_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_no_private_names_across_modules():
    _, private = _imports(_modules())
    assert private == []


def test_ruff_is_clean():
    """The lint and complexity rules in pyproject.toml hold for the package, its tests and benchmarks."""
    import subprocess
    import sys

    root = SRC.parent
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "src", "tests", "benchmarks"], cwd=root,
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-1000:]


def test_no_module_is_too_long():
    long = {m: n for m, p in _modules().items() if not m.startswith("plantsplat.raster")
            and (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}, f"modules over {MAX_LINES} lines: {long}"


def _top_level(path: Path) -> dict[str, ast.AST]:
    return {n.name: n for n in ast.parse(path.read_text()).body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}


@pytest.mark.parametrize("stage", STAGE_PACKAGES)
def test_stage_package_layout(stage):
    """``<stage>/config.py`` holds a dataclass config; ``<stage>/stage.py`` has ``run(ws, cfg, ...)``,
    ``inputs(ws, ...)`` and ``outputs(ws, ...)`` (train's outputs depend on its config: its folder, its metrics)."""
    pkg = SRC / "plantsplat" / stage
    assert (pkg / "__init__.py").is_file(), f"{stage} is not a package"
    configs = [n for n in _top_level(pkg / "config.py").values() if isinstance(n, ast.ClassDef)
               and n.name.endswith("Config") and any(getattr(d, "id", None) == "dataclass" for d in n.decorator_list)]
    assert configs, f"{stage}/config.py has no dataclass config"
    fns = _top_level(pkg / "stage.py")
    for name in ("run", "inputs", "outputs"):
        assert isinstance(fns.get(name), ast.FunctionDef), f"{stage}/stage.py has no function {name}"
    args = {name: [a.arg for a in fns[name].args.args] for name in ("run", "inputs", "outputs")}
    assert args["run"][:2] == ["ws", "cfg"] and args["inputs"][:1] == ["ws"] and args["outputs"][:1] == ["ws"], args


def test_the_cli_and_the_pipeline_load_no_heavy_library():
    """`plantsplat --help`, option parsing and `plantsplat.pipeline` stay quick: the libraries that take about a
    second to load (PyTorch, COLMAP, Open3D, OpenCV, SciPy, PyAV, matplotlib) load in the functions that use them."""
    import subprocess
    import sys

    heavy = ("torch", "pycolmap", "open3d", "cv2", "scipy", "av", "matplotlib")
    code = ("import sys, plantsplat.cli, plantsplat.pipeline, plantsplat.batch; "
            f"print(','.join(m for m in {heavy!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"loaded at import: {out}"

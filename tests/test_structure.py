"""The package's shape: no import cycle between plantsplat's modules (imports inside functions count), no module
uses another module's private names, no module is over 600 lines (raster/ aside), every stage package has the
same layout (config.py with its dataclass config, stage.py with run, inputs and outputs), imports are at module top
but for a few that defer a heavy or optional library, and the stages' tuning constants are named, not numbers in
function bodies."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
MAX_LINES = 600
"""The longest module allowed outside raster/ (the reference rasterizer and its kernels)."""
STAGE_PACKAGES = ("frames", "poses", "segment", "train", "export", "traits")
"""Every stage: each is a package with the same layout (issue 44)."""
HEAVY_LIBRARIES = ("torch", "pycolmap", "open3d", "cv2", "scipy", "av", "matplotlib", "moderngl", "numba", "plotly",
                   "gsplat", "sam2", "hydra", "omegaconf", "playwright", "ray")
"""Libraries that take about a second to load, or are optional: the only ones a function may import where it needs
them (directly, or through a plantsplat module that loads one at its top)."""
CLI_DEFERRED = ("tyro", "plantsplat.log", "plantsplat.io")
"""What ``plantsplat.cli`` defers besides: ``plantsplat --version`` answers before tyro, rich and numpy load."""
MAX_DEFERRED_IMPORTS = 60
"""Imports inside functions in the package (issue 44: 319 before; nerfstudio has 68 in 47.6k lines)."""
LITERAL_PACKAGES = ("poses", "segment", "traits")
"""The packages whose function bodies hold no tuning constant as a bare number."""
PLAIN_NUMBERS = {0, 1, 2, 3, 4, -1, 100, 255, 0.5}
"""Numbers that say what they are (indices, halves, percent, 8-bit white); so do epsilons below 1e-5."""
MAX_LITERALS = 30
"""Other numbers in the function bodies of :data:`LITERAL_PACKAGES` (issue 44: 159 before); the rest are documented
config fields or module constants."""


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


# --- imports inside functions ------------------------------------------------------------------


def _function_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement inside a function (once, however deeply nested), in source order."""
    found = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            found.update({id(n): n for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))})
    return sorted(found.values(), key=lambda n: n.lineno)


def _imported(module: str, path: Path, node: ast.Import | ast.ImportFrom, mods: dict[str, Path]) -> list[str]:
    """The modules an import statement loads (relative imports resolved; ``from pkg import submodule`` names it)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]


def _loaded_at_import(mods: dict[str, Path]) -> dict[str, set[str]]:
    """``{module: every module its import loads}``: its module-level imports, theirs, and so on (plantsplat modules
    and the other libraries by their full names)."""
    direct: dict[str, set[str]] = {}
    for m, path in mods.items():
        tree = ast.parse(path.read_text())
        deferred = {id(n) for n in _function_imports(tree)}
        names = {t for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)) and id(n) not in deferred
                 for t in _imported(m, path, n, mods)}
        direct[m] = {".".join(t.split(".")[:i]) for t in names for i in range(1, t.count(".") + 2)}
    loaded = {}
    for m in mods:
        seen, todo = set(), [m]
        while todo:
            for t in direct.get(todo.pop(), ()):
                if t not in seen:
                    seen.add(t)
                    todo.append(t)
        loaded[m] = seen
    return loaded


def _loading_heavy(mods: dict[str, Path]) -> set[str]:
    """The plantsplat modules whose import loads a heavy library."""
    return {m for m, names in _loaded_at_import(mods).items() if any(t.split(".")[0] in HEAVY_LIBRARIES for t in names)}


def _says_deferred(lines: list[str], node: ast.stmt) -> bool:
    """A comment with "deferred" on the import's lines or on the comment, import and blank lines just above it."""
    if any("deferred" in ln for ln in lines[node.lineno - 1:node.end_lineno]):
        return True
    i = node.lineno - 2
    while i >= 0 and (not lines[i].strip() or lines[i].lstrip().startswith(("#", "import ", "from "))):
        if lines[i].lstrip().startswith("#") and "deferred" in lines[i]:
            return True
        i -= 1
    return False


def _deferral_problems(module: str, path: Path, mods: dict[str, Path], heavy: set[str]) -> list[str]:
    """Each import inside a function of ``module`` that does not defer a heavy library, or does not say so."""
    text = path.read_text()
    lines = text.splitlines()
    problems = []
    for node in _function_imports(ast.parse(text)):
        names = _imported(module, path, node, mods)
        is_heavy = all(t.split(".")[0] in HEAVY_LIBRARIES or t in heavy for t in names)
        at_cli_start = module == "plantsplat.cli" and all(t in CLI_DEFERRED for t in names)
        if not (is_heavy or at_cli_start):
            problems.append(f"{module}:{node.lineno} imports {', '.join(names)} in a function: import it at the top")
        elif not _says_deferred(lines, node):
            problems.append(f"{module}:{node.lineno} defers {', '.join(names)} without a '# deferred: why' comment")
    return problems


def test_imports_inside_functions_are_few_and_each_defers_a_heavy_library():
    """Imports are at module top; a function imports only a heavy or optional library (or a plantsplat module that
    loads one), with a comment that says why, and there are at most :data:`MAX_DEFERRED_IMPORTS` of them."""
    mods = _modules()
    heavy = _loading_heavy(mods)
    count = sum(len(_function_imports(ast.parse(p.read_text()))) for p in mods.values())
    assert count <= MAX_DEFERRED_IMPORTS, f"{count} imports inside functions (at most {MAX_DEFERRED_IMPORTS})"
    problems = [x for m, p in sorted(mods.items()) for x in _deferral_problems(m, p, mods, heavy)]
    assert problems == [], "\n".join(problems)


def test_the_import_rules_find_what_they_forbid(tmp_path):
    mods = _modules()
    src = tmp_path / "fake.py"
    src.write_text("import json\n\n\ndef f():\n    import cv2  # deferred: OpenCV is slow to load\n"
                   "    import json\n    from plantsplat.segment import stage\n    import torch\n"
                   "    return json, cv2, stage, torch\n")
    problems = _deferral_problems("plantsplat.fake", src, mods, _loading_heavy(mods))
    assert len(_function_imports(ast.parse(src.read_text()))) == 4
    assert [p.split(" ", 1)[0] for p in problems] == ["plantsplat.fake:6", "plantsplat.fake:7", "plantsplat.fake:8"]
    assert "import it at the top" in problems[0] and "without a '# deferred" in problems[1]
    assert "plantsplat.segment.stage" in _loading_heavy(mods) and "plantsplat.pipeline" not in _loading_heavy(mods)


def test_only_the_poses_stage_loads_pycolmap_at_import():
    """Importing pycolmap installs glog's handlers of fatal signals over the CLI's SIGTERM handler (a SIGTERM then
    kills the process with a stack trace instead of taking the Ctrl-C path): the other stages' modules load it only in
    the function that reads a COLMAP model (``plantsplat.train.data``)."""
    loaded = _loaded_at_import(_modules())
    stages = [f"plantsplat.{s}.stage" for s in STAGE_PACKAGES if s != "poses"]
    assert {m for m in stages if "pycolmap" in loaded[m]} == set()


# --- numbers in the stages' function bodies -------------------------------------------------------


def _literals(tree: ast.AST) -> list[tuple[int, float]]:
    """``(line, value)`` of each number in a function body that is neither plain (:data:`PLAIN_NUMBERS`) nor an
    epsilon (a float below 1e-5); a nested function's numbers count for it and for the function around it."""
    found = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in (x for stmt in fn.body for x in ast.walk(stmt)):
                if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
                        and not isinstance(node.value, bool) and node.value not in PLAIN_NUMBERS \
                        and not (isinstance(node.value, float) and abs(node.value) < 1e-5):
                    found.append((node.lineno, node.value))
    return found


def test_the_stages_tuning_constants_are_named():
    """Numbers in the function bodies of poses/, segment/ and traits/ are plain ones; tuning constants are documented
    config fields (``<stage>/config.py``) and presentation constants documented module constants."""
    found = {str(p.relative_to(SRC)): n for pkg in LITERAL_PACKAGES for p in sorted((SRC / "plantsplat" / pkg).rglob("*.py"))
             if (n := _literals(ast.parse(p.read_text())))}
    count = sum(len(n) for n in found.values())
    assert count <= MAX_LITERALS, f"{count} numbers in function bodies (at most {MAX_LITERALS}): {found}"


def test_the_literal_rule_finds_numbers():
    tree = ast.parse("X = 0.7\n\n\ndef f(x, y=0.2):\n    return x * 0.3 + 0.5 + 1e-9 + 2 + -1 + 17\n")
    assert sorted(_literals(tree)) == [(5, 0.3), (5, 17)]


def test_loading_pycolmap_keeps_the_sigterm_handler(tmp_path):
    """Importing pycolmap installs glog's handlers of fatal signals over SIGTERM's; :func:`load_pycolmap` puts the
    process's own handler back, so that a SIGTERM during the poses stage takes the Ctrl-C path (issue 42 #7)."""
    import signal
    import subprocess
    import sys

    script = ("import os, signal, sys\nfrom plantsplat.pycolmap_loader import load_pycolmap\nseen = []\n"
              "signal.signal(signal.SIGTERM, lambda s, f: seen.append(s))\nload_pycolmap()\n"
              "os.kill(os.getpid(), signal.SIGTERM)\nprint('handled', seen)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and f"handled [{int(signal.SIGTERM)}]" in out.stdout, out.stderr[-2000:]

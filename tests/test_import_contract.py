"""The house's import contract: packages import only the floors below them (pyproject's
[tool.importlinter], run by `lint-imports`), no circle of files, counting imports made
inside functions and under TYPE_CHECKING as well, and an import of compd's own made inside a
function only for an optional dependency."""

from __future__ import annotations

import ast
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parent.parent
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")

# The modules of compd that a function may import where it needs them (an import inside a
# function), and why: what the daemon's package lacks or what only some configs need. Each key
# stands for itself and its submodules; the modules named after the reason (that ship with it, or
# need its dependency anyway) import it at the top like any other. Any other import of compd's own
# belongs at the top of its module: a lazy import is for an optional dependency, never to dodge a
# circle. compd/cli/ is apart: the command line imports each command's modules when that command
# runs (the start-up of `compd status` and the rest).
OPTIONAL: dict[str, tuple[str, tuple[str, ...]]] = {
    "compd.commissioning": ("compd-commissioning's: the daemon's package lacks it", ("compd.commissioning",)),
    "compd.identify": (
        "compd-commissioning's (scipy): the daemon's package lacks it",
        ("compd.identify", "compd.commissioning"),
    ),
    "compd.plant.telemetry": ("paho-mqtt and protobuf: only a config with `telemetry` starts MQTT", ()),
    "compd.plant.sparkplug": (
        "protobuf: only a config with `telemetry` speaks Sparkplug B",
        ("compd.plant.telemetry",),
    ),
    "compd.plant.opcua": ("asyncua and cryptography: only a config with `opcua` serves OPC UA", ()),
    "compd.plant.material": ("cryptography: only a config with `opcua` has certificate files", ("compd.plant.opcua",)),
}


def _import_graph():  # noqa: ANN202  (scripts/ is no package: its module, loaded from its file)
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "scripts" / "import_graph.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def circles(package: str) -> list[list[str]]:
    """The circles of modules of `package` that import each other (strongly connected sets, each
    of two modules or more), every import counted: grimp's graph, the circles found by
    scripts/import_graph.py's `circles` (the one Tarjan's of the project)."""
    graph = grimp.build_graph(package, include_external_packages=False, cache_dir=None)
    return _import_graph().circles({m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules})


def lint_imports(cwd: Path, pythonpath: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_every_package_imports_only_the_floors_below_it() -> None:
    run = lint_imports(ROOT, ROOT)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "1 kept, 0 broken" in run.stdout


def test_no_circle_of_files() -> None:
    assert circles("compd") == []


def _copy(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "compd", tmp_path / "compd", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_an_import_that_runs_up_breaks_the_contract(tmp_path: Path) -> None:
    """The ground floor importing the command line, even inside a function, is refused by name."""
    tree = _copy(tmp_path)
    frame = tree / "compd" / "core" / "frame.py"
    frame.write_text(frame.read_text() + "\n\ndef _up() -> None:\n    from compd.cli import main  # noqa: F401\n")
    run = lint_imports(tree, tree)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "compd.core is not allowed to import compd.cli" in run.stdout
    assert "compd.core.frame -> compd.cli" in run.stdout


def test_a_circle_inside_one_floor_is_found(tmp_path: Path) -> None:
    """Two files of one folder that import each other (the layers contract allows a folder's files
    to import each other; the circle test does not allow a loop)."""
    tree = _copy(tmp_path)
    clock = tree / "compd" / "core" / "clock.py"
    clock.write_text(clock.read_text() + "\n\ndef _loop() -> None:\n    from compd.core import frame  # noqa: F401\n")
    frame = tree / "compd" / "core" / "frame.py"
    frame.write_text(frame.read_text() + "\n\ndef _back() -> None:\n    from compd.core import clock  # noqa: F401\n")
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); sys.path.insert(1, sys.argv[2]);"
        "import test_import_contract as t; print(t.circles('compd'))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code, str(tree), str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tree,
    )
    assert run.returncode == 0, run.stderr
    assert "['compd.core.clock', 'compd.core.frame']" in run.stdout


def _module_name(path: Path, root: Path) -> tuple[str, str]:
    """The dotted name of a module file under `root` and the package its relative imports start from."""
    parts = path.relative_to(root).with_suffix("").parts
    if parts[-1] == "__init__":
        name = ".".join(parts[:-1])
        return name, name
    name = ".".join(parts)
    return name, name.rpartition(".")[0]


def _imported(node: ast.Import | ast.ImportFrom, package: str) -> list[str]:
    """The modules an import statement names (`from X import y` names X), relative ones resolved."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if node.level:
        base = package.split(".")[: len(package.split(".")) - node.level + 1]
        return [".".join(base + ([node.module] if node.module else []))]
    return [node.module or ""]


def lazy_imports(root: Path) -> list[tuple[str, int, str, str]]:
    """Every import of a compd module made inside a function in `root`/compd outside compd/cli/:
    (file, line, importing module, imported module)."""
    found = []
    for path in sorted((root / "compd").rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[1] == "cli":
            continue
        importer, package = _module_name(path, root)
        functions = [
            n
            for n in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
        ]
        seen = set()
        for fn in functions:
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in seen:
                    seen.add(id(node))  # an import in a nested function is walked from both
                    for module in _imported(node, package):
                        if module == "compd" or module.startswith("compd."):
                            found.append((str(rel), node.lineno, importer, module))
    return sorted(found)


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def not_optional(root: Path) -> list[str]:
    """The lazy imports of compd modules (`lazy_imports`) that OPTIONAL does not allow, as
    `file:line: importer imports module`."""
    bad = []
    for file, line, importer, module in lazy_imports(root):
        allowed = any(
            _within(module, key) and not any(_within(importer, home) for home in homes)
            for key, (_, homes) in OPTIONAL.items()
        )
        if not allowed:
            bad.append(f"{file}:{line}: {importer} imports {module} inside a function")
    return bad


def test_a_lazy_import_is_for_an_optional_dependency() -> None:
    """compd's own modules are imported inside a function only where OPTIONAL says why."""
    assert not_optional(ROOT) == []


def test_the_optional_modules_exist() -> None:
    """Every key of OPTIONAL names a module or package of compd (a renamed one is not allowed by a stale name)."""
    for key in OPTIONAL:
        path = ROOT / Path(*key.split("."))
        assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), key


def test_a_lazy_import_of_the_daemons_own_is_named(tmp_path: Path) -> None:
    """A function importing a module the daemon always has (compd.config) fails with its file and
    line; the same import of an optional module (compd.plant.opcua from the host) does not, nor
    one inside compd/cli/, nor compd.identify imported lazily from compd.commissioning's home."""
    tree = _copy(tmp_path)
    frame = tree / "compd" / "cycle" / "publish.py"
    lines = frame.read_text().count("\n")
    frame.write_text(
        frame.read_text() + "\n\ndef _late() -> None:\n    from compd.config import load_config  # noqa: F401\n"
        "    from compd.plant.opcua import OpcUaServer  # noqa: F401\n"
    )
    cli = tree / "compd" / "cli" / "tools.py"
    cli.write_text(
        cli.read_text() + "\n\ndef _late() -> None:\n    from compd.config import load_config  # noqa: F401\n"
    )
    found = not_optional(tree)
    assert found == [f"compd/cycle/publish.py:{lines + 4}: compd.cycle.publish imports compd.config inside a function"]
    assert (str(Path("compd/cycle/publish.py")), lines + 5, "compd.cycle.publish", "compd.plant.opcua") in lazy_imports(
        tree
    )

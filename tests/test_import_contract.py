"""The house's import contract: packages import only the floors below them (pyproject's
[tool.importlinter], run by `lint-imports`), and no circle of files, counting imports made
inside functions and under TYPE_CHECKING as well."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parent.parent
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def circles(package: str) -> list[list[str]]:
    """The circles of modules of `package` that import each other (strongly connected sets, each
    of two modules or more), every import counted."""
    graph = grimp.build_graph(package, include_external_packages=False, cache_dir=None)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(root: str) -> None:  # Tarjan's, iterative: no recursion limit to meet
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                ring = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    ring.append(w)
                    if w == v:
                        break
                if len(ring) > 1:
                    found.append(sorted(ring))

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return found


def lint_imports(cwd: Path, pythonpath: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run([str(LINT_IMPORTS), "--no-cache"], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


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
    code = ("import sys; sys.path.insert(0, sys.argv[1]); sys.path.insert(1, sys.argv[2]);"
            "import test_import_contract as t; print(t.circles('compd'))")
    run = subprocess.run([sys.executable, "-c", code, str(tree), str(Path(__file__).parent)],
                         capture_output=True, text=True, timeout=600, cwd=tree)
    assert run.returncode == 0, run.stderr
    assert "['compd.core.clock', 'compd.core.frame']" in run.stdout

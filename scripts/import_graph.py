"""Who imports whom among compd, hil_sim and rig, counted from every module's source (no import runs).

usage: python scripts/import_graph.py [REPO]            imports that cross a package (compd, hil_sim, rig)
       python scripts/import_graph.py --compd [REPO]    compd's own: the arrows between its folders (and
                                                        top-level modules), the circles of folders and of files
Every import counts: at module level, inside a function, under TYPE_CHECKING.
"""

from __future__ import annotations

import ast
import collections
import sys
from pathlib import Path

PACKAGES = ("compd", "hil_sim", "rig")


def imported(path: Path, modules: set[str] | dict[str, Path]) -> set[str]:
    """The modules of `modules` that `path` imports: `from a.b import c` is a.b.c where that is a
    module (a.b's __init__ is not counted for it), else a.b."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.add(sub if sub in modules else node.module)
    return {m for m in out if m in modules}


def edges(root: Path) -> collections.Counter[tuple[str, str]]:
    """(importing package, imported package.module) -> number of import statements."""
    out: collections.Counter[tuple[str, str]] = collections.Counter()
    for path in root.rglob("*.py"):
        rel = path.relative_to(root)
        if rel.parts[0] not in PACKAGES:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                parts = name.split(".")
                if parts[0] in PACKAGES and parts[0] != rel.parts[0]:
                    out[(rel.parts[0], ".".join(parts[:2]))] += 1
    return out


def file_graph(root: Path) -> dict[str, set[str]]:
    """compd's modules (dotted) -> the compd modules each imports (a package's __init__ by its name)."""
    modules = {}
    for path in sorted((root / "compd").rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        graph[name] = {m for m in imported(path, modules) if m != name and m != "compd"}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected sets of two nodes or more (Tarjan's), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                ring = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    ring.append(w)
                    if w == v:
                        break
                if len(ring) > 1:
                    found.append(sorted(ring))
    return found


def folder(module: str) -> str:
    """compd.cycle.loop -> compd.cycle; compd.config -> compd.config."""
    return ".".join(module.split(".")[:2])


def main() -> int:
    args = sys.argv[1:]
    own = "--compd" in args
    args = [a for a in args if a != "--compd"]
    root = Path(args[0]) if args else Path(__file__).resolve().parent.parent
    if not own:
        for (src, dst), n in sorted(edges(root).items()):
            print(f"{src} -> {dst}: {n}")
        return 0
    files = file_graph(root)
    arrows: collections.Counter[tuple[str, str]] = collections.Counter()
    for src, dsts in files.items():
        for dst in dsts:
            if folder(src) != folder(dst):
                arrows[(folder(src), folder(dst))] += 1
    folders: dict[str, set[str]] = collections.defaultdict(set)
    for src, dst in arrows:
        folders[src].add(dst)
        folders.setdefault(dst, set())
    for (src, dst), n in sorted(arrows.items()):
        print(f"{src} -> {dst}: {n}")
    rings = circles(dict(folders))
    print(f"circles of folders: {len(rings)}")
    for ring in rings:
        print("  " + ", ".join(ring))
    rings = circles(files)
    print(f"circles of files: {len(rings)}")
    for ring in rings:
        print("  " + ", ".join(ring))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

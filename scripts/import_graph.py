"""Who imports whom among compd, hil_sim and rig, counted from every module's source (no import runs).

usage: python scripts/import_graph.py [REPO]   (default: this repository)
Prints `package -> package.module: count` for each import that crosses a package boundary.
"""

from __future__ import annotations

import ast
import collections
import sys
from pathlib import Path

PACKAGES = ("compd", "hil_sim", "rig")


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


def main() -> int:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent
    for (src, dst), n in sorted(edges(root).items()):
        print(f"{src} -> {dst}: {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

# Splits the staged venv into the daemon package `compd` and `compd-commissioning` (scripts/build_deb.sh runs it).
"""Which staged files go into compd-commissioning; the rest stays in the daemon package compd.

The split is decided here and nowhere else, by folder: COMMISSIONING_FOLDERS are compd's own
folders (under site-packages) that only the commissioning commands import, and
COMMISSIONING_ROOTS the distributions only they need. A root takes along what it requires
that no distribution of the daemon requires (matplotlib brings fonttools and pillow,
python-dateutil stays: asyncua needs it too); the daemon's distributions are compd's other
requirements, base and runtime extras, with what they require. A root the daemon needs
after all is an error, not a silent move. Everything else the stage holds (compd's other
folders and metadata, pip, the units, the config, the docs) is the daemon's.

    python packaging/deb/split.py --site STAGE/opt/compd/venv/lib/python3.X/site-packages \
        --root STAGE --to COMMISSIONING_STAGE [--list]

moves the commissioning package's files from STAGE to COMMISSIONING_STAGE (same paths below
it) and prints what moved: per distribution and folder, its files and bytes.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import sys
from email.parser import HeaderParser
from pathlib import Path

# the one table of the split (folders relative to site-packages; distributions by name)
COMMISSIONING_FOLDERS = ("compd/identify", "compd/commissioning", "hil_sim", "rig")
COMMISSIONING_ROOTS = ("scipy", "matplotlib", "tqdm", "asyncua", "cryptography")
# the optional-dependency group of compd that is no runtime part of either package
NOT_INSTALLED_EXTRAS = ("test",)


def norm(name: str) -> str:
    """A distribution's name as PEP 503 compares them."""
    return re.sub(r"[-_.]+", "-", name).lower()


class Dist:
    """One installed distribution: its name, what it requires, the files its RECORD lists."""

    def __init__(self, info: Path) -> None:
        self.info = info
        meta = HeaderParser().parsestr((info / "METADATA").read_text(encoding="utf-8"))
        self.name = norm(str(meta["Name"]))
        self.requires = [str(r) for r in meta.get_all("Requires-Dist") or []]
        with open(info / "RECORD", encoding="utf-8", newline="") as fh:
            self.files = [row[0] for row in csv.reader(fh) if row]

    def needs(self, installed: set[str], extras: set[str]) -> set[str]:
        """The installed distributions it requires: unconditionally, or for one of `extras`."""
        out = set()
        for req in self.requires:
            m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
            if m is None:
                continue
            extra = re.search(r"""extra\s*==\s*["']([^"']+)["']""", req)
            if extra is not None and norm(extra.group(1)) not in extras:
                continue
            if norm(m.group(1)) in installed:
                out.add(norm(m.group(1)))
        return out


def closure(roots: set[str], graph: dict[str, set[str]]) -> set[str]:
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo.extend(graph.get(name, ()))
    return seen


def distributions(site: Path) -> dict[str, Dist]:
    """The distributions installed in `site`, by normalized name."""
    return {d.name: d for d in (Dist(p) for p in sorted(site.glob("*.dist-info")))}


def commissioning_distributions(dists: dict[str, Dist]) -> set[str]:
    """COMMISSIONING_ROOTS and what they require that the daemon's distributions do not."""
    if "compd" not in dists:
        raise SystemExit("split: no compd distribution installed")
    compd = dists["compd"]
    extras = {
        norm(e)
        for e in HeaderParser()
        .parsestr((compd.info / "METADATA").read_text(encoding="utf-8"))
        .get_all("Provides-Extra")
        or []
    } - {norm(e) for e in NOT_INSTALLED_EXTRAS}
    graph = {name: d.needs(set(dists), set()) for name, d in dists.items()}
    graph["compd"] = compd.needs(set(dists), extras)
    roots = {norm(r) for r in COMMISSIONING_ROOTS}
    missing = roots - set(dists)
    if missing:
        raise SystemExit(f"split: {', '.join(sorted(missing))} not installed")
    daemon = closure(graph["compd"] - roots, graph) | {"compd"}
    needed = {r: sorted(n for n in daemon if r in graph[n]) for r in roots & daemon}
    if needed:
        raise SystemExit("split: the daemon needs " + "; ".join(f"{r} (for {', '.join(b)})" for r, b in needed.items()))
    return closure(roots, graph) - daemon


def import_names(dist: Dist) -> set[str]:
    """The top-level modules and packages a distribution installs (from its RECORD)."""
    names = set()
    for f in dist.files:
        top = Path(f).parts[0]
        if top == ".." or top.endswith((".dist-info", ".libs", ".pth")) or top == "__pycache__":
            continue
        names.add(top.split(".")[0] if top.endswith((".py", ".so")) else top)
    return names


def plan(site: Path) -> tuple[dict[str, list[Path]], list[str]]:
    """{distribution or folder: the files of compd-commissioning it brings (paths under the venv's
    site-packages, possibly ../../../bin/…)}, and the daemon's distributions."""
    dists = distributions(site)
    moved: dict[str, list[Path]] = {}
    for name in sorted(commissioning_distributions(dists)):
        moved[name] = [Path(os.path.normpath(f)) for f in dists[name].files]
    for folder in COMMISSIONING_FOLDERS:
        if not (site / folder).is_dir():
            raise SystemExit(f"split: no folder {folder} in {site}")
        moved[folder] = sorted(p.relative_to(site) for p in (site / folder).rglob("*") if not p.is_dir())
    # the daemon: compd's requirements and theirs, and what nothing requires (pip, setuptools)
    return moved, sorted(set(dists) - set(moved))


def move(root: Path, site: Path, to: Path, files: list[Path]) -> int:
    """Move `files` (relative to site) from the stage `root` to the same place under `to`; their
    folders left empty are removed from the stage. The bytes moved."""
    size = 0
    for rel in files:
        src = Path(os.path.normpath(site / rel))
        if not src.is_relative_to(root):
            raise SystemExit(f"split: {rel} is outside the stage")
        if not src.exists() and not src.is_symlink():
            continue  # a RECORD line of a file pip did not keep (a byte-code file relocate.py dropped)
        dst = to / src.relative_to(root)
        dst.parent.mkdir(parents=True, exist_ok=True)
        size += src.lstat().st_size
        os.replace(src, dst)
        parent = src.parent
        while parent != root and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent
    return size


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Move compd-commissioning's files out of the staged daemon package.")
    ap.add_argument("--site", required=True, type=Path, help="the staged venv's site-packages")
    ap.add_argument("--root", required=True, type=Path, help="the daemon package's stage (the site's ancestor)")
    ap.add_argument("--to", required=True, type=Path, help="the commissioning package's stage")
    ap.add_argument("--list", action="store_true", help="say what would move, move nothing")
    args = ap.parse_args(argv)
    site, root = args.site.resolve(), args.root.resolve()
    if not site.is_relative_to(root):
        print(f"split: {site} is not under {root}", file=sys.stderr)
        return 2
    moved, daemon = plan(site)
    for name, files in moved.items():
        size = (
            sum((site / f).lstat().st_size for f in files if (site / f).exists())
            if args.list
            else move(root, site, args.to.resolve(), files)
        )
        print(f"compd-commissioning: {name}: {len(files)} files, {size / 1e6:.2f} MB")
    print(f"compd: {', '.join(daemon)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

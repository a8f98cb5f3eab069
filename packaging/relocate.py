# Makes a venv staged under DESTDIR name only its final place (scripts/install.sh runs it).
"""Relocate a staged venv to the path it will be copied to.

pip and venv write the path they ran at into the venv: console scripts' ``#!`` lines,
``bin/activate*``, ``pyvenv.cfg``'s ``command``, a local wheel's ``direct_url.json`` and
every ``.pyc`` (its source path). This rewrites the text ones to the final path (and the
rewritten scripts' hashes and sizes in their distributions' RECORD, which would otherwise
be those of the staged text: wrong, and different for every staging folder), drops
``direct_url.json`` of wheels installed from a local file (it names the build folder) and
all byte code (the installer compiles at the final path: Debian's postinst does), then
scans every file of the staged tree, binary or not, and every symlink's target for the
staging path and the build folder; any left is an error naming the files.

    python packaging/relocate.py --destdir STAGE --venv /opt/compd/venv [--forbid DIR ...] [--check-only]
        [--also TREE ...]

(--also: another staged tree to scan alike, e.g. the second package split off the stage.)
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

# pip writes this /bin/sh trampoline instead of a #! line when the interpreter's path is
# too long for the kernel (127 bytes) or holds a space: its lines 2 and 3
TRAMPOLINE = b"'''exec' "


def rewrite_scripts(bindir: Path, staged: bytes, final: bytes) -> list[Path]:
    """Point bin/'s scripts and activate* at the final venv; the files changed."""
    changed = []
    for path in sorted(bindir.iterdir()):
        if path.is_symlink() or not path.is_file():
            continue
        data = path.read_bytes()
        if staged not in data or b"\0" in data[:4096]:
            continue
        lines = data.split(b"\n")
        if lines[0] == b"#!/bin/sh" and len(lines) > 2 and lines[1].startswith(TRAMPOLINE):
            python = lines[1].split(b'"')[1].replace(staged, final)
            lines = [b"#!" + python, *lines[3:]]
            data = b"\n".join(lines)
        path.write_bytes(data.replace(staged, final))
        changed.append(path)
    return changed


def fix_records(venv: Path, changed: list[Path]) -> int:
    """Each RECORD line of a file in `changed` gets the file's hash and size as they are now; the lines changed."""
    now = {path.resolve(): path for path in changed}
    count = 0
    for record in sorted(venv.glob("lib/python*/site-packages/*.dist-info/RECORD")):
        site = record.parent.parent
        lines = record.read_bytes().split(b"\n")
        for i, line in enumerate(lines):
            name, sep, _ = line.partition(b",")
            path = (site / os.fsdecode(name)).resolve() if sep else None
            if path in now:
                data = now[path].read_bytes()
                digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=")
                end = b"\r" if line.endswith(b"\r") else b""
                lines[i] = b"%s,sha256=%s,%d%s" % (name, digest, len(data), end)
                count += 1
        record.write_bytes(b"\n".join(lines))
    return count


def rewrite_cfg(venv: Path, staged: bytes, final: bytes) -> None:
    """pyvenv.cfg's `command = ... -m venv <path>` (Python 3.11 on)."""
    cfg = venv / "pyvenv.cfg"
    cfg.write_bytes(cfg.read_bytes().replace(staged, final))


def drop_local_direct_urls(venv: Path) -> list[Path]:
    """direct_url.json of distributions installed from a local file or folder, and their RECORD line."""
    dropped = []
    for direct in sorted(venv.glob("lib/python*/site-packages/*.dist-info/direct_url.json")):
        try:
            url = json.loads(direct.read_text(encoding="utf-8")).get("url", "")
        except (OSError, ValueError):
            url = "file:"
        if not url.startswith("file:"):
            continue
        direct.unlink()
        record = direct.parent / "RECORD"
        if record.is_file():
            name = f"{direct.parent.name}/direct_url.json,"
            kept = [line for line in record.read_text(encoding="utf-8").splitlines(True) if not line.startswith(name)]
            record.write_text("".join(kept), encoding="utf-8")
        dropped.append(direct)
    return dropped


def drop_bytecode(venv: Path) -> int:
    """Remove every __pycache__ folder and stray .pyc: their source paths name the stage."""
    count = 0
    for cache in sorted(venv.rglob("__pycache__"), reverse=True):
        if cache.is_dir() and not cache.is_symlink():
            shutil.rmtree(cache)
            count += 1
    for pyc in venv.rglob("*.py[co]"):
        pyc.unlink()
        count += 1
    return count


def offenders(root: Path, needles: list[bytes]) -> list[str]:
    """Files under root whose bytes, and symlinks whose target, hold any of needles."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath, name)
            if path.is_symlink():
                if any(n in os.fsencode(os.readlink(path)) for n in needles):
                    found.append(f"{path} (symlink)")
            elif path.is_file() and any(n in path.read_bytes() for n in needles):
                found.append(str(path))
    return found


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Relocate a staged venv to the path it will be copied to.")
    ap.add_argument("--destdir", required=True, type=Path, help="the staging folder (DESTDIR)")
    ap.add_argument("--venv", required=True, help="the venv's final path, e.g. /opt/compd/venv")
    ap.add_argument("--forbid", action="append", default=[], help="another path no file may name (the build folder)")
    ap.add_argument("--check-only", action="store_true", help="change nothing: only look for files naming the folders")
    ap.add_argument(
        "--also", action="append", default=[], type=Path, help="another staged tree to scan (split off DESTDIR)"
    )
    args = ap.parse_args(argv)
    destdir = args.destdir.resolve()
    final = "/" + args.venv.strip("/")
    venv = Path(str(destdir) + final)
    if not (venv / "pyvenv.cfg").is_file():
        print(f"relocate: {venv} is not a venv", file=sys.stderr)
        return 2
    if not args.check_only:
        staged_b, final_b = os.fsencode(str(venv)), os.fsencode(final)
        fix_records(venv, rewrite_scripts(venv / "bin", staged_b, final_b))
        rewrite_cfg(venv, staged_b, final_b)
        drop_local_direct_urls(venv)
        drop_bytecode(venv)
    needles = [os.fsencode(str(destdir))] + [os.fsencode(str(Path(f).resolve())) for f in args.forbid]
    needles += [os.fsencode(str(tree.resolve())) for tree in args.also]
    left = offenders(destdir, needles) + [f for tree in args.also for f in offenders(tree.resolve(), needles)]
    if left:
        shown = ", ".join(left[:5]) + (f" and {len(left) - 5} more" if len(left) > 5 else "")
        print(f"relocate: {len(left)} staged files still name the staging or build folder: {shown}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

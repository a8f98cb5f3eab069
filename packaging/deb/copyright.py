# Writes a Debian package's copyright file: compd's own terms, then each distribution the package puts in the venv.
"""usr/share/doc/PACKAGE/copyright for the packages scripts/build_deb.sh builds (compd, compd-commissioning).

    python packaging/deb/copyright.py --package compd --site-packages STAGED_SITE --years 2026 \
        --final-site /opt/compd/venv/lib/python3.11/site-packages

The distributions are those whose .dist-info folder the package's staged site-packages holds
(packaging/deb/split.py moves each with its files).

Each distribution's license is what its own metadata says (License-Expression, else a
one-line License field, else its License classifiers); the texts are in its .dist-info
folder, which the file names at its final path.
"""

from __future__ import annotations

import argparse
import sys
from email.message import Message
from importlib.metadata import Distribution, distributions
from pathlib import Path

HEAD = """\
This is the Debian package {package} of compd, built by `make deb` (scripts/build_deb.sh).

compd (everything under /opt/compd except /opt/compd/venv, /usr/bin/compd, the
systemd units, /usr/lib/sysusers.d/compd.conf and /etc/compd/compd.yaml; and
compd's own modules in /opt/compd/venv):

  Copyright (C) {years} the compd authors
  License: proprietary (pyproject.toml: license = "LicenseRef-Proprietary").
  This file grants no rights: compd's terms are those agreed with its authors.

/opt/compd/venv holds compd and the Python distributions it runs on, installed
from their published wheels by pip, unmodified; this package ships those listed
below. Each is under its own license; the list gives, for each one, its version,
the license its metadata states, and the folder holding its license texts. The
native libraries some wheels bundle (numpy.libs, scipy.libs, pillow.libs and the
like: OpenBLAS,
the GCC Fortran and quadmath runtimes under the GCC Runtime Library Exception,
image codecs) are covered by the license texts of the wheel that bundles them.
Debian ships the common ones in /usr/share/common-licenses/ as well, e.g.
/usr/share/common-licenses/Apache-2.0, /usr/share/common-licenses/GPL-3,
/usr/share/common-licenses/LGPL-3 and /usr/share/common-licenses/MPL-2.0.

The Debian packaging (DEBIAN/, this file) is under the same terms as compd.
"""

# metadata files of a .dist-info folder that hold no license text
NOT_LICENSE = {
    "METADATA",
    "RECORD",
    "WHEEL",
    "INSTALLER",
    "REQUESTED",
    "entry_points.txt",
    "top_level.txt",
    "direct_url.json",
}


def license_of(meta: Message) -> str:
    """The license as the distribution's metadata states it, in one line."""
    expression = meta.get("License-Expression")
    if expression:
        return str(expression).strip()
    field = str(meta.get("License") or "").strip()
    if field and "\n" not in field and len(field) <= 80 and not field.lower().startswith("copyright"):
        return field
    classifiers = [
        str(c).rsplit(" :: ", 1)[-1] for c in meta.get_all("Classifier") or [] if str(c).startswith("License ::")
    ]
    if classifiers:
        return " / ".join(classifiers)
    return "see its license texts"


def dist_info(dist: Distribution) -> Path | None:
    """The distribution's .dist-info folder (from its RECORD)."""
    for file in dist.files or []:
        if file.parts and file.parts[0].endswith(".dist-info"):
            return Path(str(dist.locate_file(file.parts[0])))
    return None


def render(site: Path, final_site: str, years: str, package: str = "compd") -> str:
    lines = [HEAD.format(years=years, package=package), f"Distributions {package} puts in /opt/compd/venv:", ""]
    dists = sorted(distributions(path=[str(site)]), key=lambda d: str(d.metadata["Name"]).lower())
    for dist in dists:
        meta = dist.metadata
        name, version = str(meta["Name"]), str(meta["Version"])
        if name.lower() == "compd":
            continue
        lines.append(f"  {name} {version}")
        lines.append(f"    License: {license_of(meta)}")
        folder = dist_info(dist)
        if folder is not None:
            texts = sorted(
                p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and p.name not in NOT_LICENSE
            )
            where = f"{final_site}/{folder.name}/"
            lines.append(f"    License texts: {where}" + (f" ({', '.join(texts)})" if texts else " (none shipped)"))
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write the Debian package's copyright file to stdout.")
    ap.add_argument("--site-packages", required=True, type=Path, help="the staged venv's site-packages")
    ap.add_argument("--final-site", required=True, help="the same folder's path once installed")
    ap.add_argument("--years", required=True, help="compd's copyright years, e.g. 2025-2026")
    ap.add_argument("--package", default="compd", help="the Debian package (compd or compd-commissioning)")
    args = ap.parse_args(argv)
    if not args.site_packages.is_dir():
        print(f"copyright: no folder {args.site_packages}", file=sys.stderr)
        return 2
    sys.stdout.write(render(args.site_packages, args.final_site.rstrip("/"), args.years, args.package))
    return 0


if __name__ == "__main__":
    sys.exit(main())

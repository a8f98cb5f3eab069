"""pyproject.toml: the license as an SPDX expression (the table form warns on every build)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_license_is_an_spdx_string_and_the_build_backend_reads_it() -> None:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    license_ = data["project"]["license"]
    assert isinstance(license_, str) and re.fullmatch(r"LicenseRef-[A-Za-z0-9.\-]+|[A-Za-z0-9.\-+ ()]+", license_)
    # setuptools reads `license = "<SPDX>"` (PEP 639) from 77 on; older ones refuse it
    req = next(r for r in data["build-system"]["requires"] if r.startswith("setuptools"))
    assert int(re.search(r">=\s*(\d+)", req)[1]) >= 77, req

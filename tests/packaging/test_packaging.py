"""pyproject.toml's license; scripts/install.sh's staged tree, which names only its final paths."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RELOCATE = ROOT / "packaging" / "relocate.py"


def test_license_is_an_spdx_string_and_the_build_backend_reads_it() -> None:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    license_ = data["project"]["license"]
    assert isinstance(license_, str) and re.fullmatch(r"LicenseRef-[A-Za-z0-9.\-]+|[A-Za-z0-9.\-+ ()]+", license_)
    # setuptools reads `license = "<SPDX>"` (PEP 639) from 77 on; older ones refuse it
    req = next(r for r in data["build-system"]["requires"] if r.startswith("setuptools"))
    assert int(re.search(r">=\s*(\d+)", req)[1]) >= 77, req


def naming(root: Path, needles: list[str]) -> list[str]:
    """Files under root whose bytes, or symlinks whose target, hold any of needles."""
    found = []
    raw = [os.fsencode(n) for n in needles]
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath, name)
            data = os.fsencode(os.readlink(path)) if path.is_symlink() else path.read_bytes() if path.is_file() else b""
            if any(n in data for n in raw):
                found.append(str(path.relative_to(root)))
    return found


def fake_venv(stage: Path, final: str) -> Path:
    """What pip and venv leave in a venv staged under stage, naming the stage."""
    venv = Path(str(stage) + final)
    site = venv / "lib/python3.11/site-packages"
    (site / "pkg/__pycache__").mkdir(parents=True)
    (venv / "bin").mkdir()
    (venv / "pyvenv.cfg").write_text(f"home = /usr/bin\ncommand = /usr/bin/python3 -m venv {venv}\n")
    (venv / "bin/activate").write_text(f'VIRTUAL_ENV="{venv}"\nexport VIRTUAL_ENV\n')
    (venv / "bin/compd").write_text(f"#!{venv}/bin/python\nfrom compd.cli import main\n")
    # pip's form for an interpreter path it cannot put on a #! line
    (venv / "bin/tool").write_text(f"#!/bin/sh\n'''exec' \"{venv}/bin/python\" \"$0\" \"$@\"\n' '''\nimport tool\n")
    (venv / "bin/python").symlink_to("/usr/bin/python3")
    (site / "pkg/__init__.py").write_text("")
    (site / "pkg/__pycache__/__init__.cpython-311.pyc").write_bytes(b"\0" * 16 + os.fsencode(str(site)))
    dist = site / "pkg-1.0.dist-info"
    dist.mkdir()
    (dist / "direct_url.json").write_text(json.dumps({"url": f"file://{stage.parent}/build/pkg-1.0-py3-none-any.whl"}))
    script = record_line("../../../bin/compd", (venv / "bin/compd").read_bytes())  # pip's, of the staged text
    (dist / "RECORD").write_text(f"pkg/__init__.py,sha256=x,0\n{script}\npkg-1.0.dist-info/direct_url.json,,\n")
    return venv


def record_line(name: str, data: bytes) -> str:
    """A RECORD line as pip writes it: the path, the urlsafe base64 sha256 without padding, the size."""
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def test_relocate_points_a_staged_venv_at_its_final_path(tmp_path: Path) -> None:
    stage, final = tmp_path / "stage", "/opt/compd/venv"
    venv = fake_venv(stage, final)
    r = subprocess.run(
        [sys.executable, str(RELOCATE), "--destdir", str(stage), "--venv", final, "--forbid", str(tmp_path / "build")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert (venv / "bin/compd").read_text() == f"#!{final}/bin/python\nfrom compd.cli import main\n"
    assert (venv / "bin/tool").read_text() == f"#!{final}/bin/python\nimport tool\n"
    assert (venv / "bin/activate").read_text().startswith(f'VIRTUAL_ENV="{final}"\n')
    assert f"-m venv {final}\n" in (venv / "pyvenv.cfg").read_text()
    assert os.readlink(venv / "bin/python") == "/usr/bin/python3"
    site = venv / "lib/python3.11/site-packages"
    assert not (site / "pkg/__pycache__").exists()
    assert not (site / "pkg-1.0.dist-info/direct_url.json").exists()
    # the rewritten script's line says what it holds now, whatever the staging folder's name was
    script = record_line("../../../bin/compd", (venv / "bin/compd").read_bytes())
    assert (site / "pkg-1.0.dist-info/RECORD").read_text() == f"pkg/__init__.py,sha256=x,0\n{script}\n"
    assert naming(stage, [str(tmp_path)]) == []


def test_relocate_refuses_a_file_it_cannot_fix_naming_it_in_one_line(tmp_path: Path) -> None:
    stage, final = tmp_path / "stage", "/opt/compd/venv"
    venv = fake_venv(stage, final)
    (venv / "lib/python3.11/site-packages/pkg/_native.so").write_bytes(b"\x7fELF\0" + os.fsencode(str(stage)) + b"\0")
    (venv / "share").mkdir()
    (venv / "share/built-from.txt").write_text(f"{tmp_path}/build\n")
    r = subprocess.run(
        [sys.executable, str(RELOCATE), "--destdir", str(stage), "--venv", final, "--forbid", str(tmp_path / "build")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "2 staged files still name" in r.stderr
    assert "_native.so" in r.stderr and "built-from.txt" in r.stderr


@pytest.mark.slow
def test_install_script_stages_a_tree_that_names_only_its_final_paths(tmp_path: Path) -> None:
    stage = tmp_path / "stage"
    env = {
        **os.environ,
        "DESTDIR": str(stage),
        "PREFIX": "/opt/compd-test",
        "BINDIR": "/usr/local/bin",
        "PYTHON": sys.executable,
        "PIP_ARGS": "--no-deps --no-index",  # offline: the test checks compd's own files
    }
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "install.sh")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    # every runtime extra: all of pyproject's but the test tools
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["optional-dependencies"]
    said = re.search(r"\(extras: ([^)]*)\)", r.stdout)[1].split(",")
    assert sorted(said) == sorted(set(extras) - {"test"}) and {"metrics", "plant", "plot"} <= set(said)

    venv = stage / "opt/compd-test/venv"
    assert os.readlink(stage / "usr/local/bin/compd") == "/opt/compd-test/venv/bin/compd"
    assert (venv / "bin/compd").read_text().splitlines()[0] == "#!/opt/compd-test/venv/bin/python"
    assert not list(venv.rglob("__pycache__")) and not list(venv.rglob("*.pyc"))
    assert naming(stage, [str(tmp_path), str(ROOT)]) == []
    # a venv with pip, which works where it stands too
    pip = subprocess.run(
        [str(venv / "bin/python"), "-m", "pip", "--version"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    assert pip.returncode == 0 and pip.stdout.startswith("pip "), pip.stderr

    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return  # the run at the final path needs a mount namespace (root; CI is root)
    # at its final path (a private mount namespace: the host's /opt is untouched), the venv's compd
    # validates the shipped config (dependencies from this interpreter's site-packages: --no-deps)
    deps = sysconfig.get_paths()["purelib"]
    script = (
        'set -e; mount -t tmpfs tmpfs /opt; mkdir /opt/compd-test; mount --bind "$1/opt/compd-test" /opt/compd-test; '
        '/opt/compd-test/venv/bin/compd check-config "$1/etc/compd/compd.yaml"; '
        "/opt/compd-test/venv/bin/python -c 'import compd; print(compd.__file__)'"
    )
    run = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh", str(stage)],
        env={**os.environ, "PYTHONPATH": deps},
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "ok" and re.fullmatch(
        r"/opt/compd-test/venv/lib/python3\.\d+/site-packages/compd/__init__\.py", lines[1]
    )

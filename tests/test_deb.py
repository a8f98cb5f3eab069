"""`make deb`'s package: lintian, its contents, no build path inside, an install in a throw-away root."""

from __future__ import annotations

import hashlib
import marshal
import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

from tests.test_packaging import naming

ROOT = Path(__file__).resolve().parent.parent
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
UNITDIR = "lib/systemd/system"
VENV = "/opt/compd/venv"

# the package is built once for the module (a minute or two); the build, lintian and the install each
# take tens of seconds on a loaded 2-core machine
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def tool(name: str, package: str) -> str:
    """A tool the tests need; its absence fails them (`make sysdeps` installs it), never skips them."""
    exe = shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed (Debian package {package}; `make sysdeps`)")
    return exe


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the .deb, the folder it was built in) from scripts/build_deb.sh, into a temp folder of its own."""
    tool("dpkg-shlibdeps", "dpkg-dev")
    out = tmp_path_factory.mktemp("debbuild")
    env = {k: v for k, v in os.environ.items() if k not in {"PYTHONPATH", "VIRTUAL_ENV", "KEEP_STAGE"}}
    # xz at level 1: the same files as `make deb`'s level 6, in a tenth of the compression time
    env["DEB_COMPRESS_LEVEL"] = "1"
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "build_deb.sh"), "--out", str(out)],
        env=env, capture_output=True, text=True, timeout=840, cwd=out,
    )
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    arch = subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True, check=True).stdout.strip()
    deb = out / f"compd_{VERSION}-1_{arch}.deb"
    assert deb.is_file(), sorted(p.name for p in out.iterdir())
    assert not (out / "deb").exists(), "the staging folder is removed after the build"
    return deb, out


@pytest.fixture(scope="module")
def deb(built: tuple[Path, Path]) -> Path:
    return built[0]


@pytest.fixture(scope="module")
def tree(deb: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package's files and control files (DEBIAN/), as dpkg-deb --raw-extract lays them out."""
    where = tmp_path_factory.mktemp("debtree") / "x"
    subprocess.run(["dpkg-deb", "--raw-extract", str(deb), str(where)], check=True, timeout=300)
    return where


def field(deb: Path, name: str) -> str:
    return subprocess.run(["dpkg-deb", "--field", str(deb), name], capture_output=True, text=True, check=True).stdout.strip()


def test_lintian_reports_no_error_and_every_override_is_used(deb: Path) -> None:
    lintian = tool("lintian", "lintian")
    r = subprocess.run(
        [lintian, "--fail-on", "error", "--display-info", str(deb)], capture_output=True, text=True, timeout=840
    )
    tags = [line for line in r.stdout.splitlines() if re.match(r"^[EWIPX]: ", line)]
    assert r.returncode == 0, r.stdout + r.stderr
    assert not [t for t in tags if t.startswith(("E:", "W:"))], "\n".join(tags)
    assert not [t for t in tags if "unused-override" in t or "mismatched-override" in t], "\n".join(tags)
    # without the overrides lintian does complain: they are what silences it, each for a stated reason
    overrides = (ROOT / "packaging" / "deb" / "lintian-overrides").read_text(encoding="utf-8").split("\n\n")
    for block in overrides[1:]:
        lines = block.strip().splitlines()
        assert lines[0].startswith("#") and any(line.startswith("compd: ") for line in lines), block


def test_contents_units_conffile_and_control(deb: Path, tree: Path) -> None:
    listing = subprocess.run(["dpkg-deb", "--contents", str(deb)], capture_output=True, text=True, check=True).stdout
    entries: dict[str, tuple[str, str]] = {}
    for line in listing.splitlines():
        mode, owner, _size, _date, _time, rest = line.split(None, 5)
        name, _, target = rest.partition(" -> ")
        entries[name.removeprefix("./").rstrip("/")] = (mode, owner)
        if name == "./usr/bin/compd":
            assert mode.startswith("l") and target == f"{VENV}/bin/compd", line
    assert {owner for _, owner in entries.values()} == {"root/root"}
    assert entries[f"{VENV[1:]}/bin/compd"][0] == "-rwxr-xr-x"
    for path in (
        "usr/bin/compd", f"{UNITDIR}/compd.service", f"{UNITDIR}/compd@.service", "etc/compd/compd.yaml",
        "usr/lib/sysusers.d/compd.conf", "usr/share/doc/compd/copyright", "usr/share/doc/compd/changelog.Debian.gz",
        "usr/share/man/man1/compd.1.gz", "usr/share/lintian/overrides/compd", f"{VENV[1:]}/bin/pip",
        "opt/compd/docs/commissioning.md", "opt/compd/systemd/realtime.conf.example",
    ):
        assert path in entries, path
    assert not [p for p in entries if p.endswith((".pyc", "__pycache__"))], "byte code is the postinst's"
    # the units run the venv's compd on the shipped config
    unit = (tree / UNITDIR / "compd.service").read_text(encoding="utf-8")
    assert f"ExecStart={VENV}/bin/compd run /etc/compd/compd.yaml" in unit.splitlines()
    assert (tree / "etc/compd/compd.yaml").read_bytes() == (ROOT / "configs/service.yaml").read_bytes()

    assert field(deb, "Package") == "compd"
    assert field(deb, "Version") == f"{VERSION}-1"
    assert field(deb, "Architecture") == subprocess.run(
        ["dpkg", "--print-architecture"], capture_output=True, text=True, check=True).stdout.strip()
    assert re.fullmatch(r".+ <[^@\s]+@[^@\s]+\.[a-z]+>", field(deb, "Maintainer"))
    assert field(deb, "Description").startswith("real-time thermal-error compensation daemon")
    depends = [d.strip() for d in field(deb, "Depends").split(",")]
    python = os.path.realpath("/usr/bin/python3")  # what build_deb.sh builds the venv on
    assert re.fullmatch(r"python3\.\d+", Path(python).name) and Path(python).name in depends, depends
    assert any(d.startswith("libc6 (>= ") for d in depends) and "adduser" in depends, depends
    # ... and the venv runs on that interpreter
    assert os.readlink(tree / VENV[1:] / "bin" / Path(python).name) == python

    info = subprocess.run(["dpkg-deb", "--info", str(deb)], capture_output=True, text=True, check=True).stdout
    for script in ("postinst", "prerm", "postrm"):
        # dpkg-deb --info marks an executable control file with a *
        assert re.search(rf"\*\s+{script}\s+#!/bin/sh", info), info
        path = tree / "DEBIAN" / script
        assert path.stat().st_mode & 0o777 == 0o755
        assert subprocess.run(["sh", "-n", str(path)], capture_output=True).returncode == 0
    assert (tree / "DEBIAN/conffiles").read_text() == "/etc/compd/compd.yaml\n"
    # md5sums covers every file, and says their content
    sums = {}
    for line in (tree / "DEBIAN/md5sums").read_text().splitlines():
        digest, name = line.split("  ", 1)
        sums[name] = digest
    files = {p.relative_to(tree).as_posix() for p in tree.rglob("*") if p.is_file() and not p.is_symlink()}
    assert set(sums) == {f for f in files if not f.startswith("DEBIAN/")}
    for name in ("etc/compd/compd.yaml", f"{VENV[1:]}/bin/compd", f"{UNITDIR}/compd.service"):
        assert hashlib.md5((tree / name).read_bytes()).hexdigest() == sums[name]


def test_nothing_in_the_package_names_the_build_or_the_checkout(built: tuple[Path, Path], tree: Path) -> None:
    _, out = built
    named = naming(tree, [str(out), str(ROOT)])
    assert not named, named
    # what used to name it: the #! lines, activate, pyvenv.cfg
    venv = tree / VENV[1:]
    assert (venv / "bin/compd").read_text().splitlines()[0] == f"#!{VENV}/bin/python"
    assert (venv / "bin/pip").read_text().splitlines()[0].startswith(f"#!{VENV}/bin/python")
    assert re.search(rf'^VIRTUAL_ENV="?{VENV}"?$', (venv / "bin/activate").read_text(), re.M)
    assert f"-m venv {VENV}" in (venv / "pyvenv.cfg").read_text()


NS_SCRIPT = r"""
set -eu
x=$1; upper=$2; work=$3; res=$4
run() {  # run NAME CMD...: its output and exit code into $res, whatever it returns
    name=$1; shift
    set +e; "$@" >"$res/$name.out" 2>&1; echo $? >"$res/$name.rc"; set -e
}
# this mount namespace only: a fresh /opt and /run (hiding the host's, and any /opt/compd on it),
# the package's files at their final places, /etc and sysusers.d as overlays that take the writes
mount -t tmpfs tmpfs /run
mount -t tmpfs tmpfs /opt
mkdir /opt/compd
mount --bind "$x/opt/compd" /opt/compd
mount -t overlay overlay -o "lowerdir=$x/etc:/etc,upperdir=$upper,workdir=$work" /etc
mount -t overlay overlay -o "lowerdir=$x/usr/bin:/usr/bin" /usr/bin
mount -t overlay overlay -o "lowerdir=$x/usr/lib/sysusers.d:/usr/lib/sysusers.d" /usr/lib/sysusers.d
cd /
run postinst sh "$x/DEBIAN/postinst" configure
# an upgrade (configure with the version it replaces): with compd not running, then with systemd
# saying two units run (a systemctl of this namespace's, on PATH)
run upgrade sh "$x/DEBIAN/postinst" configure 0.0.9-1
mkdir -p /run/systemd/system /opt/fakebin
printf '#!/bin/sh\ncase "$*" in *list-units*) printf "compd.service loaded active running compd\\ncompd@lathe1.service loaded active running compd (lathe1)\\n" ;; esac\n' >/opt/fakebin/systemctl
chmod +x /opt/fakebin/systemctl
run upgrade_running env PATH="/opt/fakebin:$PATH" sh "$x/DEBIAN/postinst" configure 0.0.9-1
rm -rf /run/systemd
run id id compd
as_compd="setpriv --reuid=compd --regid=compd --init-groups"
run version $as_compd /usr/bin/compd --version
run check $as_compd /usr/bin/compd check-config /etc/compd/compd.yaml
cp /etc/compd/compd.yaml /opt/telemetry.yaml
printf 'telemetry:\n  host: 127.0.0.1\n  group_id: plant\n  edge_node_id: cell1\n  device_id: spindle\n' >>/opt/telemetry.yaml
run telemetry $as_compd /usr/bin/compd check-config /opt/telemetry.yaml
run extras $as_compd /opt/compd/venv/bin/python -c 'import paho.mqtt.client, asyncua, prometheus_client, matplotlib, rich; print("ok")'
run pip /opt/compd/venv/bin/python -m pip --version
run pipcheck /opt/compd/venv/bin/python -m pip check
find /opt/compd/venv -name '*.pyc' >"$res/pycs"
cp "$(find /opt/compd/venv/lib -path '*/site-packages/compd/cli/__pycache__/*.pyc' | head -n1)" "$res/sample.pyc"
run prerm sh "$x/DEBIAN/prerm" remove
find /opt/compd/venv -name __pycache__ >"$res/left"
run postrm sh "$x/DEBIAN/postrm" purge
"""


def test_installs_and_runs_in_a_throw_away_root(deb: Path, tmp_path: Path) -> None:
    """dpkg-deb -x, then in a private mount namespace the files at their final paths, the maintainer scripts run."""
    if os.geteuid() != 0:
        pytest.skip("needs root: mount namespaces and the postinst's user (`make test` runs as root on CI)")
    tool("unshare", "util-linux")
    x, upper, work, res = (tmp_path / n for n in ("x", "upper", "work", "res"))
    for d in (upper, work, res):
        d.mkdir()
    subprocess.run(["dpkg-deb", "--raw-extract", str(deb), str(x)], check=True, timeout=300)
    passwd = Path("/etc/passwd").read_bytes()
    had_user = b"\ncompd:" in b"\n" + passwd
    script = tmp_path / "ns.sh"
    script.write_text(NS_SCRIPT)
    r = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", str(script), str(x), str(upper), str(work), str(res)],
        capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr

    def out(name: str) -> str:
        rc = int((res / f"{name}.rc").read_text())
        text = (res / f"{name}.out").read_text()
        assert rc == 0, f"{name}: exit {rc}: {text}"
        return text

    postinst = out("postinst")
    assert "neither enabled nor started" in postinst and "systemctl enable --now compd" in postinst
    assert had_user or "created the system user compd" in postinst
    # after an upgrade it names what still runs the old code and says restart, not reload
    assert out("upgrade").strip() == "compd: upgraded from 0.0.9-1; compd is not running: it starts on this version."
    running = out("upgrade_running")
    assert "upgraded from 0.0.9-1; still running the old version: compd.service compd@lathe1.service." in running
    assert "systemctl restart compd.service compd@lathe1.service" in running and "not reload" in running
    assert re.search(r"groups=.*\(dialout\)", out("id"))
    assert out("version").strip() == f"compd {VERSION}"
    assert out("check").strip() == "ok"
    assert out("telemetry").strip() == "ok"
    # (matplotlib first says it cannot write a config folder in root's HOME: compd has none)
    assert out("extras").strip().splitlines()[-1] == "ok"
    assert f"from {VENV}/lib/python3." in out("pip")
    assert "No broken requirements found" in out("pipcheck")
    # the postinst compiled the venv where it runs: the byte code names /opt/compd, not the build
    assert len((res / "pycs").read_text().split()) > 1000
    code = marshal.loads((res / "sample.pyc").read_bytes()[16:])  # after the 16-byte header
    assert code.co_filename.startswith(f"{VENV}/lib/python3."), code.co_filename
    out("prerm")
    assert (res / "left").read_text() == "", "prerm leaves no byte code for dpkg to trip over"
    out("postrm")
    # the host's own /etc was never written: the user lives in the overlay's upper layer
    assert Path("/etc/passwd").read_bytes() == passwd
    assert had_user or b"\ncompd:" in b"\n" + (upper / "passwd").read_bytes()

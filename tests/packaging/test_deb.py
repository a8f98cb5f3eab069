"""`make deb`'s two packages, compd (the daemon) and compd-commissioning: lintian, their contents and sizes,
no build path inside, their times clamped to the source's, an install of the daemon alone and then of both
in a throw-away root. (`make deb-twice` builds them twice and compares the bytes: make accept runs it.)"""

from __future__ import annotations

import hashlib
import marshal
import os
import re
import shutil
import subprocess
import tarfile
import tomllib
from pathlib import Path

import pytest

from tests.packaging.test_packaging import naming

ROOT = Path(__file__).resolve().parents[2]
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
UNITDIR = "lib/systemd/system"
VENV = "/opt/compd/venv"
PACKAGES = ("compd", "compd-commissioning")
# the daemon's install at most a third of the single package's (336 MB), in MB of 10^6 bytes
DAEMON_MAX_MB = 112.0

# the packages are built once for the module (a few minutes); the build, lintian and the install each
# take tens of seconds on a loaded 2-core machine
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def tool(name: str, package: str) -> str:
    """A tool the tests need; its absence fails them (`make sysdeps` installs it), never skips them."""
    exe = shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed (Debian package {package}; `make sysdeps`)")
    return exe


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Path], Path]:
    """({package: its .deb}, the folder they were built in) from scripts/build_deb.sh, into a temp folder of its own."""
    tool("dpkg-shlibdeps", "dpkg-dev")
    out = tmp_path_factory.mktemp("debbuild")
    # the source's date the build takes (the last commit's): read now, a commit during the build would move it
    (out / "epoch").write_text(last_commit_time())
    env = {
        k: v for k, v in os.environ.items() if k not in {"PYTHONPATH", "VIRTUAL_ENV", "KEEP_STAGE", "SOURCE_DATE_EPOCH"}
    }
    # xz at level 1: the same files as `make deb`'s level 6, in a tenth of the compression time
    env["DEB_COMPRESS_LEVEL"] = "1"
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "build_deb.sh"), "--out", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=840,
        cwd=out,
    )
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    arch = subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True, check=True).stdout.strip()
    debs = {name: out / f"{name}_{VERSION}-1_{arch}.deb" for name in PACKAGES}
    assert sorted(p.name for p in out.glob("*.deb")) == sorted(d.name for d in debs.values())
    assert not (out / "deb").exists(), "the staging folder is removed after the build"
    return debs, out


@pytest.fixture(scope="module")
def deb(built: tuple[dict[str, Path], Path]) -> Path:
    """The daemon package."""
    return built[0]["compd"]


@pytest.fixture(scope="module")
def cdeb(built: tuple[dict[str, Path], Path]) -> Path:
    """The commissioning package."""
    return built[0]["compd-commissioning"]


def extract(deb: Path, where: Path) -> Path:
    """A package's files and control files (DEBIAN/), as dpkg-deb --raw-extract lays them out."""
    subprocess.run(["dpkg-deb", "--raw-extract", str(deb), str(where)], check=True, timeout=300)
    return where


@pytest.fixture(scope="module")
def tree(deb: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return extract(deb, tmp_path_factory.mktemp("debtree") / "x")


@pytest.fixture(scope="module")
def ctree(cdeb: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return extract(cdeb, tmp_path_factory.mktemp("debtree") / "c")


def field(deb: Path, name: str) -> str:
    return subprocess.run(
        ["dpkg-deb", "--field", str(deb), name], capture_output=True, text=True, check=True
    ).stdout.strip()


def override_file(package: str) -> Path:
    return (
        ROOT / "packaging" / "deb" / ("lintian-overrides" if package == "compd" else "commissioning.lintian-overrides")
    )


@pytest.mark.parametrize("package", PACKAGES)
def test_lintian_reports_no_error_and_every_override_is_used(built: tuple[dict[str, Path], Path], package: str) -> None:
    lintian = tool("lintian", "lintian")
    r = subprocess.run(
        [lintian, "--fail-on", "error", "--display-info", str(built[0][package])],
        capture_output=True,
        text=True,
        timeout=840,
    )
    tags = [line for line in r.stdout.splitlines() if re.match(r"^[EWIPX]: ", line)]
    assert r.returncode == 0, r.stdout + r.stderr
    assert not [t for t in tags if t.startswith(("E:", "W:"))], "\n".join(tags)
    assert not [t for t in tags if "unused-override" in t or "mismatched-override" in t], "\n".join(tags)
    # without the overrides lintian does complain: they are what silences it, each for a stated reason
    overrides = override_file(package).read_text(encoding="utf-8").split("\n\n")
    for block in overrides[1:]:
        lines = block.strip().splitlines()
        assert lines[0].startswith("#") and any(line.startswith(f"{package}: ") for line in lines), block
        assert all(line.startswith(("#", f"{package}: ")) for line in lines), block


def contents(deb: Path) -> dict[str, tuple[str, str, str]]:
    """{path: (mode, owner, symlink target)} of a package's files and folders, as dpkg-deb --contents lists them."""
    listing = subprocess.run(["dpkg-deb", "--contents", str(deb)], capture_output=True, text=True, check=True).stdout
    entries: dict[str, tuple[str, str, str]] = {}
    for line in listing.splitlines():
        mode, owner, _size, _date, _time, rest = line.split(None, 5)
        name, _, target = rest.partition(" -> ")
        entries[name.removeprefix("./").rstrip("/")] = (mode, owner, target)
    return entries


def test_contents_units_conffile_and_control(deb: Path, tree: Path) -> None:
    entries = contents(deb)
    assert entries["usr/bin/compd"][0].startswith("l") and entries["usr/bin/compd"][2] == f"{VENV}/bin/compd"
    assert {owner for _, owner, _ in entries.values()} == {"root/root"}
    assert entries[f"{VENV[1:]}/bin/compd"][0] == "-rwxr-xr-x"
    for path in (
        "usr/bin/compd",
        f"{UNITDIR}/compd.service",
        f"{UNITDIR}/compd@.service",
        "etc/compd/compd.yaml",
        "usr/lib/sysusers.d/compd.conf",
        "usr/share/doc/compd/copyright",
        "usr/share/doc/compd/changelog.Debian.gz",
        "usr/share/man/man1/compd.1.gz",
        "usr/share/lintian/overrides/compd",
        f"{VENV[1:]}/bin/pip",
        "opt/compd/docs/commissioning.md",
        "opt/compd/systemd/realtime.conf.example",
    ):
        assert path in entries, path
    assert not [p for p in entries if p.endswith((".pyc", "__pycache__"))], "byte code is the postinst's"
    # the units run the venv's compd on the shipped config
    unit = (tree / UNITDIR / "compd.service").read_text(encoding="utf-8")
    assert f"ExecStart={VENV}/bin/compd run /etc/compd/compd.yaml" in unit.splitlines()
    assert (tree / "etc/compd/compd.yaml").read_bytes() == (ROOT / "configs/service.yaml").read_bytes()

    assert field(deb, "Package") == "compd"
    assert field(deb, "Version") == f"{VERSION}-1"
    assert (
        field(deb, "Architecture")
        == subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True, check=True).stdout.strip()
    )
    assert re.fullmatch(r".+ <[^@\s]+@[^@\s]+\.[a-z]+>", field(deb, "Maintainer"))
    assert field(deb, "Description").startswith("real-time thermal-error compensation daemon")
    assert field(deb, "Suggests") == "compd-commissioning"
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


def site_packages(entries: dict[str, tuple[str, str, str]]) -> str:
    """The venv's site-packages folder as a package lists it (opt/compd/venv/lib/python3.X/site-packages)."""
    return next(p for p in entries if re.fullmatch(rf"{VENV[1:]}/lib/python3\.\d+/site-packages", p))


def test_the_commissioning_package_and_the_split(deb: Path, cdeb: Path, ctree: Path) -> None:
    """compd-commissioning: compd's commissioning folders, the simulator, the rig, scipy, matplotlib and
    the OPC UA stack, no file of the daemon's (dpkg refuses two packages with one file), depending on
    compd of its very version; the daemon keeps the rest."""
    daemon, comm = contents(deb), contents(cdeb)
    site = site_packages(comm)
    assert site == site_packages(daemon)
    files = {p for p, (mode, _, _) in comm.items() if not mode.startswith("d")}
    assert not files & {p for p, (mode, _, _) in daemon.items() if not mode.startswith("d")}
    assert {owner for _, owner, _ in comm.values()} == {"root/root"}
    for folder in (
        "compd/identify",
        "compd/commissioning",
        "hil_sim",
        "rig",
        "scipy",
        "matplotlib",
        "asyncua",
        "cryptography",
        "tqdm",
    ):
        assert f"{site}/{folder}/__init__.py" in comm and f"{site}/{folder}" not in daemon, folder
    for folder in (
        "compd/cli",
        "compd/daemon",
        "compd/core",
        "compd/plant",
        "numpy",
        "pymodbus",
        "pydantic",
        "yaml",
        "paho",
        "prometheus_client",
        "rich",
    ):
        assert f"{site}/{folder}/__init__.py" in daemon and f"{site}/{folder}" not in comm, folder
    assert f"{site}/compd/plant/opcua.py" in daemon  # compd's own server: its stack (asyncua) is the other's
    for path in (
        "usr/share/doc/compd-commissioning/copyright",
        "usr/share/doc/compd-commissioning/changelog.Debian.gz",
        "usr/share/lintian/overrides/compd-commissioning",
    ):
        assert path in comm, path
    assert not [p for p in files if p.startswith(("etc/", "lib/", "usr/bin/", "usr/lib/"))], "the daemon's places"
    assert not [p for p in comm if p.endswith((".pyc", "__pycache__"))], "byte code is the postinst's"
    assert field(cdeb, "Package") == "compd-commissioning" and field(cdeb, "Source") == "compd"
    assert field(cdeb, "Version") == field(deb, "Version") and field(cdeb, "Architecture") == field(deb, "Architecture")
    depends = [d.strip() for d in field(cdeb, "Depends").split(",")]
    assert depends[0] == f"compd (= {VERSION}-1)", depends
    copyright_ = (ctree / "usr/share/doc/compd-commissioning/copyright").read_text(encoding="utf-8")
    assert "  scipy " in copyright_ and "  numpy " not in copyright_
    for script in ("postinst", "prerm"):
        path = ctree / "DEBIAN" / script
        assert path.stat().st_mode & 0o777 == 0o755
        assert subprocess.run(["sh", "-n", str(path)], capture_output=True).returncode == 0
    assert not (ctree / "DEBIAN/conffiles").exists() and not (ctree / "DEBIAN/postrm").exists()


def du_mb(tree: Path) -> float:
    """The installed files' disk use (du -sk after dpkg -x, DEBIAN/ left out), MB of 10^6 bytes."""
    kib = subprocess.run(["du", "-sk", "--exclude=DEBIAN", str(tree)], capture_output=True, text=True, check=True)
    return int(kib.stdout.split()[0]) * 1024 / 1e6


def test_sizes_the_daemon_a_third_of_the_one_package(deb: Path, cdeb: Path, tree: Path, ctree: Path) -> None:
    """The figures docs/commissioning.md states, measured as it says (printed: pytest -s)."""
    for name, package, where in (("compd", deb, tree), ("compd-commissioning", cdeb, ctree)):
        print(
            f"{name}: .deb {package.stat().st_size / 1e6:.1f} MB, Installed-Size"
            f" {int(field(package, 'Installed-Size')) * 1024 / 1e6:.1f} MB, du {du_mb(where):.1f} MB"
        )
    assert int(field(deb, "Installed-Size")) * 1024 / 1e6 <= DAEMON_MAX_MB
    assert du_mb(tree) <= DAEMON_MAX_MB
    assert int(field(cdeb, "Installed-Size")) > int(field(deb, "Installed-Size"))


def last_commit_time() -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), "log", "-1", "--format=%ct"], capture_output=True, text=True, check=True
    ).stdout.strip()


def test_every_time_in_the_packages_is_the_sources_at_most(built: tuple[dict[str, Path], Path]) -> None:
    """The reproducible build's cheap half: the ar members dated SOURCE_DATE_EPOCH (the last commit's),
    no file newer (the full check, two builds and their sha256, is `make deb-twice`)."""
    epoch = int((built[1] / "epoch").read_text())
    for deb in built[0].values():
        data = deb.read_bytes()
        assert data.startswith(b"!<arch>\n")
        at, dates = 8, []
        while at < len(data):
            header = data[at : at + 60]
            dates.append(int(header[16:28]))
            at += 60 + int(header[48:58]) + (int(header[48:58]) % 2)
        assert dates == [epoch] * 3, dates  # debian-binary, control.tar, data.tar
        with subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE) as proc:
            assert proc.stdout is not None
            with tarfile.open(fileobj=proc.stdout, mode="r|") as tar:
                newer = [m.name for m in tar if m.mtime > epoch]
        assert proc.returncode == 0 and newer == [], newer[:5]
        assert int(field(deb, "Installed-Size")) > 0


def test_nothing_in_the_packages_names_the_build_or_the_checkout(
    built: tuple[dict[str, Path], Path], tree: Path, ctree: Path
) -> None:
    _, out = built
    for where in (tree, ctree):
        named = naming(where, [str(out), str(ROOT)])
        assert not named, named
    # what used to name it: the #! lines, activate, pyvenv.cfg
    venv = tree / VENV[1:]
    assert (venv / "bin/compd").read_text().splitlines()[0] == f"#!{VENV}/bin/python"
    assert (venv / "bin/pip").read_text().splitlines()[0].startswith(f"#!{VENV}/bin/python")
    assert re.search(rf'^VIRTUAL_ENV="?{VENV}"?$', (venv / "bin/activate").read_text(), re.M)
    assert f"-m venv {VENV}" in (venv / "pyvenv.cfg").read_text()


NS_SCRIPT = r"""
set -eu
x=$1; c=$2; upper=$3; work=$4; res=$5
run() {  # run NAME CMD...: its output and exit code into $res, whatever it returns
    name=$1; shift
    set +e; "$@" >"$res/$name.out" 2>&1; echo $? >"$res/$name.rc"; set -e
}
# this mount namespace only: a fresh /opt and /run (hiding the host's, and any /opt/compd on it),
# the daemon package's files at their final places, /etc and sysusers.d as overlays that take the writes
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
printf '#!/bin/sh\ncase "$*" in *list-units*) printf "compd.service loaded active running'\
' compd\\ncompd@lathe1.service loaded active running compd (lathe1)\\n" ;; esac\n' >/opt/fakebin/systemctl
chmod +x /opt/fakebin/systemctl
run upgrade_running env PATH="/opt/fakebin:$PATH" sh "$x/DEBIAN/postinst" configure 0.0.9-1
rm -rf /run/systemd
run id id compd
as_compd="setpriv --reuid=compd --regid=compd --init-groups"
run version $as_compd /usr/bin/compd --version

# the daemon alone: a machine's config checks and runs; the shipped one's simulator, a fit and the OPC
# UA server's stack name compd-commissioning
mkdir /opt/machine
printf 't_s,T_xi,err_z_um\n' >/opt/machine/day.csv
i=0; while [ $i -lt 120 ]; do printf '%d,%d.5,%d.0\n' $((i * 60)) $((20 + i / 20)) $((i / 20 * 2)) \
>>/opt/machine/day.csv; i=$((i + 1)); done
printf 'loop: {clock: sim, period_s: 60.0, speedup: 0}\nsources: [{kind: replay, name: log, path: day.csv}]\nmodel:'\
' {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 13.6e-6, length_mm: 165.0}}\nguard:'\
' {stale_after_s: 120.0}\nsink: {kind: pci1756}\nstatus: {path: status.json}\nlog: {path: log.csv, period_s:'\
' 60}\nmetrics: {enabled: true, bind: 127.0.0.1, port: 0}\ntelemetry: {host: 127.0.0.1, group_id: plant,'\
' edge_node_id: cell1, device_id: spindle}\n' >/opt/machine/machine.yaml
chown -R compd:compd /opt/machine
cd /opt/machine
run alone_check $as_compd /usr/bin/compd check-config machine.yaml
sed -i '/^telemetry:/d' machine.yaml
run alone_run $as_compd /usr/bin/compd run machine.yaml
run alone_shipped $as_compd /usr/bin/compd check-config /etc/compd/compd.yaml
run alone_fit $as_compd /usr/bin/compd fit --kind mlr --log day.csv --out model.yaml
run alone_extras $as_compd /opt/compd/venv/bin/python -c 'import paho.mqtt.client, prometheus_client, rich, numpy,'\
' pymodbus, can, serial; print("ok")'
run alone_absent /opt/compd/venv/bin/python -c 'import importlib.util as u; print(sorted(n for n in ("scipy",'\
' "matplotlib", "hil_sim", "rig", "asyncua", "cryptography", "tqdm", "compd.identify", "compd.commissioning") if'\
' u.find_spec(n) is not None))'
run alone_pipcheck /opt/compd/venv/bin/python -m pip check
cd /

# then compd-commissioning beside it: today's single package, whole
cp -a "$c/opt/compd/." /opt/compd/
run cpostinst sh "$c/DEBIAN/postinst" configure
run check $as_compd /usr/bin/compd check-config /etc/compd/compd.yaml
cp /etc/compd/compd.yaml /opt/telemetry.yaml
printf 'telemetry:\n  host: 127.0.0.1\n  group_id: plant\n  edge_node_id: cell1\n  device_id: spindle\n' \
>>/opt/telemetry.yaml
run telemetry $as_compd /usr/bin/compd check-config /opt/telemetry.yaml
run extras $as_compd /opt/compd/venv/bin/python -c 'import paho.mqtt.client, asyncua, prometheus_client, matplotlib,'\
' rich, scipy, hil_sim, rig.bench, compd.identify, compd.commissioning; print("ok")'
cd /opt/machine
run fit $as_compd /usr/bin/compd fit --kind mlr --log day.csv --out model.yaml
cd /
run pip /opt/compd/venv/bin/python -m pip --version
run pipcheck /opt/compd/venv/bin/python -m pip check
find /opt/compd/venv -name '*.pyc' >"$res/pycs"
cp "$(find /opt/compd/venv/lib -path '*/site-packages/compd/cli/__pycache__/*.pyc' | head -n1)" "$res/sample.pyc"
# compd-commissioning's prerm takes its byte code (dpkg-query -L lists its files: a stand-in on PATH)
printf '#!/bin/sh\ncat %s\n' "$res/cfiles" >/opt/fakebin/dpkg-query
chmod +x /opt/fakebin/dpkg-query
run cprerm env PATH="/opt/fakebin:$PATH" sh "$c/DEBIAN/prerm" remove
find /opt/compd/venv -name '*.pyc' >"$res/pycs_left"
run prerm sh "$x/DEBIAN/prerm" remove
find /opt/compd/venv -name __pycache__ >"$res/left"
run postrm sh "$x/DEBIAN/postrm" purge
"""


def test_installs_and_runs_in_a_throw_away_root(deb: Path, cdeb: Path, tmp_path: Path) -> None:
    """dpkg-deb -x, then in a private mount namespace the files at their final paths, the maintainer scripts
    run: the daemon package alone, then compd-commissioning beside it."""
    if os.geteuid() != 0:
        pytest.skip("needs root: mount namespaces and the postinst's user (`make test` runs as root on CI)")
    tool("unshare", "util-linux")
    x, c, upper, work, res = (tmp_path / n for n in ("x", "c", "upper", "work", "res"))
    for d in (upper, work, res):
        d.mkdir()
    extract(deb, x)
    extract(cdeb, c)
    # what `dpkg-query -L compd-commissioning` says once it is installed: its files at their final paths
    listing = subprocess.run(["dpkg-deb", "--contents", str(cdeb)], capture_output=True, text=True, check=True).stdout
    names = (
        line.split(None, 5)[5].partition(" -> ")[0].removeprefix("./").rstrip("/") for line in listing.splitlines()
    )
    (res / "cfiles").write_text("".join(f"/{name}\n" for name in names))
    passwd = Path("/etc/passwd").read_bytes()
    had_user = b"\ncompd:" in b"\n" + passwd
    script = tmp_path / "ns.sh"
    script.write_text(NS_SCRIPT)
    # the packages' python must see the packages only: no checkout on PYTHONPATH (pytest's, make's)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "COMPD"))}
    r = subprocess.run(
        [
            "unshare",
            "--mount",
            "--propagation",
            "private",
            "sh",
            str(script),
            str(x),
            str(c),
            str(upper),
            str(work),
            str(res),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert r.returncode == 0, r.stdout + r.stderr

    def out(name: str, rc: int = 0) -> str:
        got = int((res / f"{name}.rc").read_text())
        text = (res / f"{name}.out").read_text()
        assert got == rc, f"{name}: exit {got}: {text}"
        return text

    postinst = out("postinst")
    assert "neither enabled nor started" in postinst and "systemctl enable --now compd" in postinst
    assert "compd-commissioning" in postinst
    assert had_user or "created the system user compd" in postinst
    # after an upgrade it names what still runs the old code and says restart, not reload
    assert out("upgrade").strip() == "compd: upgraded from 0.0.9-1; compd is not running: it starts on this version."
    running = out("upgrade_running")
    assert "upgraded from 0.0.9-1; still running the old version: compd.service compd@lathe1.service." in running
    assert "systemctl restart compd.service compd@lathe1.service" in running and "not reload" in running
    assert re.search(r"groups=.*\(dialout\)", out("id"))
    assert out("version").strip() == f"compd {VERSION}"

    # the daemon package alone
    assert out("alone_check").strip() == "ok"
    assert "compd: 120 cycles, 0 missed" in out("alone_run")
    assert (
        out("alone_shipped", 2)
        .strip()
        .endswith(
            "sources[0].kind: source kind 'sim' is part of the compd-commissioning package, which is not installed"
        )
    )
    assert out("alone_fit", 2) == "compd fit: part of the compd-commissioning package, which is not installed\n"
    assert out("alone_extras").strip().splitlines()[-1] == "ok"
    assert out("alone_absent").strip() == "[]"
    # pip knows compd's metadata asks for scipy and tqdm (the commissioning package's), and says only that
    missing = out("alone_pipcheck", 1).strip().splitlines()
    assert sorted(missing) == [
        f"compd {VERSION} requires scipy, which is not installed.",
        f"compd {VERSION} requires tqdm, which is not installed.",
    ], missing

    # with compd-commissioning: all of today's single package
    out("cpostinst")
    assert out("check").strip() == "ok"
    assert out("telemetry").strip() == "ok"
    # (matplotlib first says it cannot write a config folder in root's HOME: compd has none)
    assert out("extras").strip().splitlines()[-1] == "ok"
    assert "mlr axis z" in out("fit")
    assert f"from {VENV}/lib/python3." in out("pip")
    assert "No broken requirements found" in out("pipcheck")
    # the postinsts compiled the venv where it runs: the byte code names /opt/compd, not the build
    pycs = (res / "pycs").read_text().split()
    assert len(pycs) > 1000 and any("/site-packages/scipy/" in p for p in pycs)
    code = marshal.loads((res / "sample.pyc").read_bytes()[16:])  # after the 16-byte header
    assert code.co_filename.startswith(f"{VENV}/lib/python3."), code.co_filename
    # compd-commissioning's prerm takes its own byte code and leaves compd's
    out("cprerm")
    left = (res / "pycs_left").read_text().split()
    assert any("/site-packages/compd/cli/__pycache__/" in p for p in left)
    ours = (
        "/site-packages/scipy/",
        "/site-packages/matplotlib/",
        "/site-packages/hil_sim/",
        "/site-packages/compd/identify/",
    )
    assert not [p for p in left if any(o in p for o in ours)], left[:5]
    out("prerm")
    assert (res / "left").read_text() == "", "prerm leaves no byte code for dpkg to trip over"
    out("postrm")
    # the host's own /etc was never written: the user lives in the overlay's upper layer
    assert Path("/etc/passwd").read_bytes() == passwd
    assert had_user or b"\ncompd:" in b"\n" + (upper / "passwd").read_bytes()

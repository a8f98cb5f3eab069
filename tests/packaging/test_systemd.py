"""The systemd units: they verify, they start compd to READY under a notify socket, they install."""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from compd.service.notify import socket_address
from tests.service_helpers import sim_config

ROOT = Path(__file__).resolve().parents[2]
UNITS = ("compd.service", "compd@.service")
COMPD = "/opt/compd/venv/bin/compd"


def unit_entries(path: Path) -> list[tuple[str, str, str]]:
    """(section, key, value) of a unit file, in order (keys may repeat)."""
    out, section = [], ""
    for raw in path.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.append((section, key.strip(), value.strip()))
    return out


def unit_values(path: Path) -> dict[str, str]:
    return {k: v for _, k, v in unit_entries(path)}


def systemd_analyze() -> str:
    """The systemd-analyze binary; its absence fails the test (make sysdeps installs it), never skips it."""
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.fail("systemd-analyze is not installed (Debian package systemd; `make sysdeps`)")
    return exe


def composed(tmp_path: Path, name: str, *drop_ins: str) -> Path:
    """The unit with drop-ins appended, as one file (systemd merges repeated [Service] sections)."""
    text = "".join((ROOT / "systemd" / f).read_text(encoding="utf-8") + "\n" for f in (name, *drop_ins))
    out = tmp_path / name.replace("@", "-at-")
    out.write_text(text, encoding="utf-8")
    return out


def exposure(unit: Path) -> float:
    r = subprocess.run(
        [systemd_analyze(), "security", "--offline=true", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", r.stdout + r.stderr)
    assert m, r.stdout + r.stderr
    return float(m.group(1))


_GROUPS: dict[str, set[str]] = {}


def syscalls(name: str) -> set[str]:
    """A system call, or the calls of a `@group` (nested groups expanded) per systemd-analyze."""
    if not name.startswith("@"):
        return {name}
    if name not in _GROUPS:
        r = subprocess.run(
            [systemd_analyze(), "syscall-filter", "--no-pager", name], capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 0, r.stderr
        out: set[str] = set()
        for line in r.stdout.splitlines()[1:]:
            word = line.strip()
            if word and not word.startswith("#"):
                out |= syscalls(word)
        _GROUPS[name] = out
    return _GROUPS[name]


def allowed_syscalls(entries: list[tuple[str, str, str]]) -> set[str]:
    """The allow list that the unit's SystemCallFilter= lines make, in systemd.exec(5)'s order:
    the first line (not `~`) starts an allow list with @default, later lines add to it,
    `~` lines take away, an empty assignment starts over."""
    allowed: set[str] | None = None
    for _, key, value in entries:
        if key != "SystemCallFilter":
            continue
        if not value:
            allowed = None
            continue
        deny = value.startswith("~")
        names = set().union(*(syscalls(w) for w in value.lstrip("~").split()))
        if allowed is None:
            assert not deny, "compd's units use an allow list"
            allowed = syscalls("@default")
        allowed = allowed - names if deny else allowed | names
    assert allowed is not None, "no SystemCallFilter"
    return allowed


def capability_set(entries: list[tuple[str, str, str]], key: str) -> set[str]:
    caps: set[str] = set()
    for _, k, value in entries:
        if k == key:
            caps = caps | set(value.split()) if value else set()
    return caps


@pytest.mark.parametrize("name", UNITS)
def test_unit_has_the_service_settings(name):
    v = unit_values(ROOT / "systemd" / name)
    assert v["Type"] == "notify" and v["NotifyAccess"] == "main"
    assert v["WatchdogSec"] and v["Restart"] == "on-failure"
    assert int(v["StartLimitBurst"]) <= 10 and v["StartLimitIntervalSec"]
    assert v["RestartPreventExitStatus"] == "2"
    assert v["User"] == "compd" and v["SupplementaryGroups"] == "dialout"
    assert v["StateDirectory"].startswith("compd") and v["LogsDirectory"].startswith("compd")
    for key in ("ProtectHome", "PrivateTmp", "NoNewPrivileges"):
        assert v[key] == "yes", key
    assert v["ProtectSystem"] == "strict"
    assert v["CapabilityBoundingSet"] == "" and v["AmbientCapabilities"] == ""  # realtime.conf adds two
    assert set(v["RestrictAddressFamilies"].split()) == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_CAN"}
    assert v["UMask"] == "0077" and v["MemoryDenyWriteExecute"] == "yes"
    assert v["IPAddressDeny"] == "any" and v["IPAddressAllow"] == "localhost"
    assert v["DevicePolicy"] == "closed" and v["SystemCallErrorNumber"] == "EPERM"
    devices = {val.split()[0] for _, k, val in unit_entries(ROOT / "systemd" / name) if k == "DeviceAllow"}
    assert devices == {"char-ttyS", "char-ttyUSB", "char-ttyACM"}  # serial ports; CAN is a netdev
    assert shlex.split(v["ExecReload"]) == ["/bin/kill", "-HUP", "$MAINPID"]  # `systemctl reload compd`
    exe, cmd, cfg = shlex.split(v["ExecStart"])
    assert (exe, cmd) == (COMPD, "run") and cfg.startswith("/etc/compd/")
    assert shlex.split(v["ExecStartPre"])[:2] == [COMPD, "check-config"]


def test_realtime_drop_in_is_opt_in():
    v = unit_values(ROOT / "systemd" / "realtime.conf.example")
    assert v["RestrictRealtime"] == "no"
    assert v["LimitRTPRIO"] and v["LimitMEMLOCK"] == "infinity"
    assert set(v["AmbientCapabilities"].split()) <= {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    assert unit_values(ROOT / "systemd" / "compd.service")["RestrictRealtime"] == "yes"


@pytest.mark.parametrize("name", UNITS)
def test_security_exposure_is_at_most_1_5(name):
    """systemd-analyze security: 2.5 before the sandbox was tightened (DeviceAllow, ProtectProc,
    no capabilities, ~@privileged ~@resources, IPAddressDeny, MemoryDenyWriteExecute, UMask)."""
    assert exposure(ROOT / "systemd" / name) <= 1.5


@pytest.mark.parametrize("name", UNITS)
def test_realtime_drop_in_still_grants_what_realtime_py_needs(tmp_path, name):
    base = unit_entries(ROOT / "systemd" / name)
    unit = composed(tmp_path, name, "realtime.conf.example")
    entries = unit_entries(unit)
    need = {"sched_setscheduler", "sched_setaffinity", "mlockall"}  # compd/cycle/realtime.py
    assert need <= allowed_syscalls(entries)
    assert not {"sched_setscheduler", "sched_setaffinity"} & allowed_syscalls(base)  # opt-in only
    for key in ("CapabilityBoundingSet", "AmbientCapabilities"):
        assert capability_set(entries, key) == {"CAP_SYS_NICE", "CAP_IPC_LOCK"}, key
        assert capability_set(base, key) == set(), key
    v = unit_values(unit)
    assert v["RestrictRealtime"] == "no" and int(v["LimitRTPRIO"]) >= 50 and v["LimitMEMLOCK"] == "infinity"
    # systemd reads the composition the same way: the drop-in opens exactly these checks
    r = subprocess.run(
        [systemd_analyze(), "security", "--offline=true", "--json=short", str(unit)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    failed = {t["name"] for t in json.loads(r.stdout) if t["set"] is False}
    assert {
        "SystemCallFilter=~@resources",
        "CapabilityBoundingSet=~CAP_SYS_(NICE|RESOURCE)",
        "CapabilityBoundingSet=~CAP_IPC_LOCK",
        "RestrictRealtime=",
    } <= failed


def test_network_drop_in_names_only_documentation_addresses():
    """The example must not point compd at anyone's real network: RFC 5737 / RFC 3849 prefixes."""
    docs = [ipaddress.ip_network(n) for n in ("192.0.2.0/24", "198.51.100.0/24", "203.0.113.0/24", "2001:db8::/32")]
    lines = (ROOT / "systemd" / "network.conf.example").read_text(encoding="utf-8").splitlines()
    allowed = [ln.lstrip("#").partition("=")[2].split() for ln in lines if ln.lstrip("#").startswith("IPAddressAllow=")]
    nets = [ipaddress.ip_network(a, strict=False) for words in allowed for a in words]
    assert nets and all(any(n.version == d.version and n.subnet_of(d) for d in docs) for n in nets)
    v = unit_values(ROOT / "systemd" / "network.conf.example")
    assert "IPAddressDeny" not in v  # it only adds to the unit's allow list


def test_systemd_analyze_verify(tmp_path):
    """Offline verify; ExecStart must name an existing file, so the venv's path is swapped in."""
    exe = shutil.which("compd") or sys.executable
    for name in UNITS:
        text = (ROOT / "systemd" / name).read_text(encoding="utf-8").replace(COMPD, exe)
        (tmp_path / name).write_text(text, encoding="utf-8")
    shutil.copy(tmp_path / "compd@.service", tmp_path / "compd@lathe1.service")
    for d in ("compd.service.d", "compd@.service.d"):
        (tmp_path / d).mkdir()
        for drop_in in ("realtime", "network"):
            shutil.copy(ROOT / "systemd" / f"{drop_in}.conf.example", tmp_path / d / f"{drop_in}.conf")
    env = {**os.environ, "SYSTEMD_UNIT_PATH": f"{tmp_path}:"}
    for unit in ("compd.service", "compd@lathe1.service"):
        r = subprocess.run(
            [systemd_analyze(), "verify", str(tmp_path / unit)],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert r.returncode == 0, r.stderr
        lines = [ln for ln in r.stderr.splitlines() if "compd" in ln]
        assert lines == [], "\n".join(lines)


def test_unit_command_reaches_ready_pings_the_watchdog_and_stops_on_sigterm(tmp_path):
    unit = unit_values(ROOT / "systemd" / "compd.service")
    config = sim_config(tmp_path, duration_s=36000, period_s=0.5, speedup=3600)

    def adapt(cmdline: str) -> list[str]:  # the unit's command line, in this venv
        argv = shlex.split(cmdline)
        assert argv[0] == COMPD and argv[-1] == "/etc/compd/compd.yaml"
        return [sys.executable, "-m", "compd", *argv[1:-1], str(config)]

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for setting in unit.get("Environment", "").split():
        k, _, v = setting.partition("=")
        env[k] = v
    pre = subprocess.run(adapt(unit["ExecStartPre"]), env=env, capture_output=True, text=True, timeout=60)
    assert pre.returncode == 0 and pre.stdout.strip() == "ok", pre.stderr

    name = f"@compd-test-notify-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(socket_address(name))
    sock.settimeout(30)
    env.update(NOTIFY_SOCKET=name, WATCHDOG_USEC="200000")
    proc = subprocess.Popen(
        adapt(unit["ExecStart"]), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        messages = [sock.recv(4096).decode()]
        assert messages[0].splitlines()[0] == "READY=1"
        while "WATCHDOG=1" not in messages:
            messages.append(sock.recv(4096).decode())
        proc.send_signal(signal.SIGTERM)
        while not any(m.startswith("STOPPING=1") for m in messages):
            messages.append(sock.recv(4096).decode())
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        sock.close()
    assert proc.returncode == 0, err
    assert "cycles" in out
    assert "event=start" in err and "event=stop" in err
    assert any(m.startswith("STATUS=") or "\nSTATUS=" in m for m in messages)


@pytest.mark.slow
def test_install_script_stages_everything(tmp_path):
    stage = tmp_path / "stage"
    env = {
        **os.environ,
        "DESTDIR": str(stage),
        "PREFIX": "/opt/compd-test",
        "PYTHON": sys.executable,
        "PIP_ARGS": "--no-deps --no-index",  # offline: the test checks compd's own files
    }
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "install.sh")], env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stdout + r.stderr
    unit = stage / "etc/systemd/system/compd.service"
    v = unit_values(unit)
    assert v["ExecStart"] == "/opt/compd-test/venv/bin/compd run /etc/compd/compd.yaml"
    assert (stage / "etc/systemd/system/compd@.service").is_file()
    assert (stage / "usr/lib/sysusers.d/compd.conf").read_text().count("compd") >= 2
    for drop_in in ("realtime.conf.example", "network.conf.example"):
        assert (stage / "opt/compd-test/systemd" / drop_in).is_file()
    for doc in ("configuration.md", "commissioning.md", "troubleshooting.md"):
        assert (stage / "opt/compd-test/docs" / doc).is_file()
    config = stage / "etc/compd/compd.yaml"
    assert config.read_text() == (ROOT / "configs" / "service.yaml").read_text()
    # the venv's compd validates the installed config (dependencies from this interpreter's site-packages);
    # its console script names the final path (/opt/compd-test/...), so the staged interpreter runs it
    deps = sysconfig.get_paths()["purelib"]
    check = subprocess.run(
        [str(stage / "opt/compd-test/venv/bin/python"), "-m", "compd", "check-config", str(config)],
        env={**os.environ, "PYTHONPATH": deps},
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert check.returncode == 0 and check.stdout.strip() == "ok", check.stderr
    where = subprocess.run(
        [str(stage / "opt/compd-test/venv/bin/python"), "-c", "import compd; print(compd.__file__)"],
        env={**os.environ, "PYTHONPATH": deps},
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert str(stage) in where.stdout
    # a second install keeps the user's config
    config.write_text(config.read_text() + "# edited\n")
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "install.sh")], env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0 and "keeping the existing" in r.stdout
    assert config.read_text().endswith("# edited\n")

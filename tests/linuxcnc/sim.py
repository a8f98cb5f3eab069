"""A headless LinuxCNC sim mill for a test: started, homed, driven and stopped leaving nothing behind.

`Sim` writes a machine into a folder of its own under /tmp (an INI: mm, X Y Z on trivkins, external
offsets on X and Z; Debian's basic_sim.tcl for the HAL; a display script of its own instead of a GUI),
runs `linuxcnc` on it as root with an unprivileged RTAPI_UID (LinuxCNC refuses root otherwise) in its
own process group, and waits until the display script has reset the estop, turned the machine on and
homed every axis. The test then talks to the machine through HAL (`halcmd`, `getp`, a userspace
component of its own made with compd.io.hal_modules' `hal`) and through `linuxcnc.stat()` (`stat()`);
`run_program` asks the display script to run a G-code file in auto mode.

The display script (Debian's /usr/bin/python3, `DISPLAY_SCRIPT`) is the machine's GUI: LinuxCNC shuts
down when it exits, which it does when the Sim writes its `stop` file (or it is signalled). Commands
reach it as files (`command-N`, answered by `reply-N`), so nothing but the files is shared.

LinuxCNC is one per machine: its HAL and NML shared memory have fixed keys and its lock file is
/tmp/linuxcnc.lock (a second `linuxcnc` started beside a first one shuts the first one down). So a
Sim holds an flock on `SIM_LOCK` from start to stop (Sims of other pytest processes wait their turn)
and refuses to start beside a LinuxCNC that is not its own. `stop` leaves nothing: LinuxCNC's own
shutdown, then whatever of it is still alive (found by a token in its environment: rtapi_app and
linuxcncsvr make sessions of their own) signalled and waited for, `halrun -U` when rtapi_app was
among them, its shared memory and /tmp files removed.

A HAL component made in the test process must be `exit()`ed before the Sim stops: LinuxCNC's shutdown
(`halcmd unload all`) SIGTERMs the process of every userspace component, which would end the test run.
`stop` ignores SIGTERM while such a component is loaded and then fails naming it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any

import pytest

from compd.io import hal_modules

COMMANDS = ("linuxcnc", "halcmd", "halrun")  # Debian's linuxcnc-uspace (Makefile APT_PACKAGES_BARE)
SIM_LOCK = Path("/tmp/compd-linuxcnc-sim.lock")  # one Sim at a time on this machine, across processes
LINUXCNC_LOCK = Path("/tmp/linuxcnc.lock")  # LinuxCNC's own "it is running" file
RTAPI_UID = 65534  # nobody: the uid LinuxCNC's real-time part runs as (never root)
TOKEN_VAR = "COMPD_LINUXCNC_SIM"  # in the environment of every process of a Sim: how its leftovers are found
# programs of LinuxCNC's that hold a machine: one of these without our token is someone else's LinuxCNC
LINUXCNC_PROGRAMS = ("rtapi_app", "linuxcncsvr", "milltask")
# LinuxCNC's System V shared memory keys: HAL, RTAPI, the uspace UUID, motion (hal_lib, motmod), and the
# NML buffers of Debian's linuxcnc.nml (1001..1005)
NML_FILE = Path("/usr/share/linuxcnc/linuxcnc.nml")  # Debian's; the Sim's copy has no TCP server (see INI)
SHM_KEYS = (0x48414C32, 0x90280A48, 0x48484C34, 100, 1001, 1002, 1003, 1004, 1005)
POLL_S = 0.05

INI = """\
# compd's test mill: machine units mm, X Y Z on trivkins, external offsets on X and Z, homed in place
[EMC]
MACHINE = compd test mill
VERSION = 1.1
NML_FILE = {nml}

[DISPLAY]
DISPLAY = {display}

[TASK]
TASK = milltask
CYCLE_TIME = 0.010

[RS274NGC]
PARAMETER_FILE = sim.var

[EMCIO]
EMCIO = io
CYCLE_TIME = 0.100
TOOL_TABLE = tool.tbl

[EMCMOT]
EMCMOT = motmod
SERVO_PERIOD = 1000000

[HAL]
HALFILE = LIB:basic_sim.tcl -no_use_hal_manualtoolchange

[TRAJ]
COORDINATES = XYZ
LINEAR_UNITS = mm
ANGULAR_UNITS = degree
MAX_LINEAR_VELOCITY = 50

[KINS]
JOINTS = 3
KINEMATICS = trivkins coordinates=XYZ

[AXIS_X]
OFFSET_AV_RATIO = {ratio}
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -10
MAX_LIMIT = 500

[AXIS_Y]
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -10
MAX_LIMIT = 400

[AXIS_Z]
OFFSET_AV_RATIO = {ratio}
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -300
MAX_LIMIT = 10

[JOINT_0]
TYPE = LINEAR
HOME_SEQUENCE = 0
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -10
MAX_LIMIT = 500

[JOINT_1]
TYPE = LINEAR
HOME_SEQUENCE = 0
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -10
MAX_LIMIT = 400

[JOINT_2]
TYPE = LINEAR
HOME_SEQUENCE = 0
MAX_VELOCITY = 50
MAX_ACCELERATION = 500
MIN_LIMIT = -300
MAX_LIMIT = 10
"""

TOOL_TABLE = "T1 P1 D6.0 Z0 ;6 mm end mill\n"

# The machine's GUI: runs under Debian's Python (LinuxCNC's `linuxcnc` module is Debian's), started by
# `linuxcnc` as `display.py -ini INI`. Every wait also watches for the stop file and signals, so a Sim
# that gives up (or a test that ends) never waits on a display stuck in a loop.
DISPLAY_SCRIPT = '''\
#!/usr/bin/python3 -u
"""compd's test display for a headless LinuxCNC: homes the machine, writes `ready`, then runs the
commands the Sim writes (`command-N`: `run PATH`, answered in `reply-N`) until `stop` appears."""
import os
import signal
import sys
import time

import linuxcnc

HERE = os.path.dirname(os.path.abspath(__file__))
signalled = []


def on_signal(signum, frame):
    signalled.append(signum)


for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(sig, on_signal)


def log(*what):
    print("display:", *what, flush=True)


def stopping():
    return bool(signalled) or os.path.exists(os.path.join(HERE, "stop"))


def connect():
    while not stopping():
        try:
            return linuxcnc.stat(), linuxcnc.command(), linuxcnc.error_channel()
        except linuxcnc.error as exc:  # the NML buffers not there yet
            log("waiting for LinuxCNC:", exc)
            time.sleep(0.2)
    return None


def errors_seen():
    out = []
    while True:
        got = errors.poll()
        if not got:
            return out
        log("error channel:", got[1])
        out.append(got[1])


def until(done):
    while not stopping():
        stat.poll()
        if done():
            return True
        errors_seen()
        time.sleep(0.05)
    return False


def ask(do, done):
    """Send a command until its effect shows (milltask may still be starting)."""
    while not stopping():
        do()
        command.wait_complete(5.0)
        stat.poll()
        if done():
            return True
        errors_seen()
        time.sleep(0.2)
    return False


def home():
    return (
        ask(lambda: command.state(linuxcnc.STATE_ESTOP_RESET),
            lambda: stat.task_state in (linuxcnc.STATE_ESTOP_RESET, linuxcnc.STATE_ON))
        and ask(lambda: command.state(linuxcnc.STATE_ON), lambda: stat.task_state == linuxcnc.STATE_ON)
        and ask(lambda: command.mode(linuxcnc.MODE_MANUAL), lambda: stat.task_mode == linuxcnc.MODE_MANUAL)
        and ask(lambda: command.teleop_enable(0), lambda: stat.motion_mode == linuxcnc.TRAJ_MODE_FREE)
        and ask(lambda: command.home(-1), lambda: True)
        and until(lambda: all(stat.homed[i] for i in range(3)))
        and ask(lambda: command.teleop_enable(1), lambda: stat.motion_mode == linuxcnc.TRAJ_MODE_TELEOP)
    )


def run(path):
    errors_seen()
    if not ask(lambda: command.mode(linuxcnc.MODE_AUTO), lambda: stat.task_mode == linuxcnc.MODE_AUTO):
        return "error: stopped"
    command.program_open(path)
    command.wait_complete(10.0)
    command.auto(linuxcnc.AUTO_RUN, 0)
    serial = command.serial  # taken by task once its status echoes it (wait_complete would wait out the run)
    until(lambda: stat.echo_serial_number >= serial)
    seen = errors_seen()
    return "error: " + " / ".join(seen) if seen else "ok"


def answer(name):
    number = name.split("-", 1)[1]
    with open(os.path.join(HERE, name)) as fh:
        words = fh.read().split(None, 1)
    os.unlink(os.path.join(HERE, name))
    log("command", number, words)
    if len(words) == 2 and words[0] == "run":
        reply = run(words[1].strip())
    else:
        reply = "error: unknown command %r" % (words,)
    log("reply", number, reply)
    tmp = os.path.join(HERE, "reply-%s.tmp" % number)
    with open(tmp, "w") as fh:
        fh.write(reply)
    os.rename(tmp, os.path.join(HERE, "reply-" + number))


log("started", sys.argv[1:])
connected = connect()
if connected is None:
    sys.exit(0)
stat, command, errors = connected
if not home():
    log("stopped before the machine was homed")
    sys.exit(0)
stat.poll()
log("homed", stat.homed[:3])
with open(os.path.join(HERE, "ready.tmp"), "w") as fh:
    fh.write("homed\\n")
os.rename(os.path.join(HERE, "ready.tmp"), os.path.join(HERE, "ready"))
while not stopping():
    names = sorted((n for n in os.listdir(HERE) if n.startswith("command-") and not n.endswith(".tmp")),
                   key=lambda n: int(n.split("-", 1)[1]))
    for name in names:
        answer(name)
    errors_seen()
    time.sleep(0.05)
log("exits", "on signal %s" % signalled[0] if signalled else "on the stop file")
'''


class SimError(RuntimeError):
    """The sim did not do what was asked (did not start, a command failed); the message has LinuxCNC's output."""


def require() -> tuple[ModuleType, ModuleType]:
    """LinuxCNC's commands and Python modules, or the test FAILS (never skips) naming `make sysdeps`."""
    missing = [name for name in COMMANDS if shutil.which(name) is None]
    if missing:
        pytest.fail(
            f"LinuxCNC's {', '.join(missing)} not installed (Debian package linuxcnc-uspace; `make sysdeps`)",
            pytrace=False,
        )
    reason = hal_modules.available()
    if reason is not None:
        pytest.fail(reason, pytrace=False)
    return hal_modules.load()


def wait_for(cond: Callable[[], Any], what: str, timeout_s: float = 60.0) -> Any:
    """Poll `cond` until it returns something true (returned); SimError naming `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = cond()
        if got:
            return got
        if time.monotonic() > deadline:
            raise SimError(f"{what}: not within {timeout_s} s")
        time.sleep(POLL_S)


class Sim:
    """A headless LinuxCNC sim mill (context manager): `start()` returns once it is on and homed; `stop()`.

    folder      its own folder under /tmp (world-writable: RTAPI_FIFO_PATH is there, for uid RTAPI_UID),
                removed by a clean `stop()` unless `keep`
    ini, log    the INI and LinuxCNC's output (its stdout and stderr, the display script's too)
    start_s, stop_s   how long start and stop took (s)
    """

    def __init__(self, *, offset_av_ratio: float = 0.2, keep: bool = False) -> None:
        require()  # before anything is made
        self.offset_av_ratio = offset_av_ratio
        self.keep = keep
        self.folder = Path(tempfile.mkdtemp(prefix="compd-linuxcnc-"))
        self.folder.chmod(0o1777)
        self.ini = self.folder / "sim.ini"
        self.log = self.folder / "linuxcnc.log"
        self.display = self.folder / "display.py"
        self.token = uuid.uuid4().hex
        self.env = {
            "PATH": "/usr/sbin:/usr/bin:/sbin:/bin",
            "HOME": str(self.folder),  # where `linuxcnc` copies its logs when it fails
            "LANG": "C.UTF-8",
            "RTAPI_UID": str(RTAPI_UID),
            "RTAPI_FIFO_PATH": str(self.folder / ".rtapi_fifo"),
            TOKEN_VAR: self.token,
        }
        self.start_s: float | None = None
        self.stop_s: float | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock_fd: int | None = None
        self._tmp_before: set[str] = set()
        self._commands = 0

    # ---- the machine's files

    def _write_machine(self) -> None:
        self.display.write_text(DISPLAY_SCRIPT)
        self.display.chmod(0o755)
        # Debian's NML buffers without their TCP=5005 option: linuxcncsvr would listen on 0.0.0.0:5005 for
        # remote GUIs; the Sim's are local (shared memory, the same keys)
        nml = self.folder / "linuxcnc.nml"
        nml.write_text(NML_FILE.read_text().replace(" TCP=5005", ""))
        self.ini.write_text(INI.format(display=self.display, ratio=self.offset_av_ratio, nml=nml))
        (self.folder / "tool.tbl").write_text(TOOL_TABLE)

    # ---- start

    def __enter__(self) -> Sim:
        return self.start()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.stop()

    def start(self, timeout_s: float = 120.0) -> Sim:
        """Run LinuxCNC and wait (up to `timeout_s`) until it is on and homed; SimError with its output if not."""
        if self._proc is not None or self.stop_s is not None:
            raise SimError("a Sim starts once: make another one")
        self._write_machine()
        began = time.monotonic()
        deadline = began + timeout_s
        try:
            self._take_lock(deadline)
            foreign = processes(LINUXCNC_PROGRAMS, without=self.token)
            if foreign:
                raise SimError(
                    f"another LinuxCNC runs on this machine ({_describe(foreign)}); one at a time: "
                    f"stop it (or `halrun -U`) first"
                )
            self._tmp_before = linuxcnc_tmp_files()
            with open(self.log, "wb") as log:  # the child holds its own copy of the descriptor
                self._proc = subprocess.Popen(
                    ["linuxcnc", "-r", str(self.ini)],  # -r: output to our log, not to /tmp files
                    cwd=self.folder,
                    env=self.env,
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
            while not (self.folder / "ready").exists():
                if self._proc.poll() is not None:
                    raise SimError(f"linuxcnc exited ({self._proc.returncode}) before the machine was homed")
                if time.monotonic() > deadline:
                    raise SimError(f"the machine was not on and homed within {timeout_s} s")
                time.sleep(POLL_S)
        except BaseException as exc:
            self.keep = True  # the log stays for whoever reads the failure
            try:
                self.stop()
            finally:
                if isinstance(exc, SimError):
                    raise SimError(f"{exc} (folder {self.folder}); LinuxCNC's output ends:\n{self.tail()}") from None
            raise
        self.start_s = time.monotonic() - began
        return self

    def _take_lock(self, deadline: float) -> None:
        fd = os.open(SIM_LOCK, os.O_RDWR | os.O_CREAT, 0o666)
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise SimError(f"another Sim held {SIM_LOCK} until the deadline") from None
                time.sleep(0.2)
        self._lock_fd = fd

    # ---- the test's side

    @property
    def pid(self) -> int | None:
        """The `linuxcnc` script's process id (its process group's too) while it runs."""
        return self._proc.pid if self._proc is not None and self._proc.poll() is None else None

    def tail(self, lines: int = 40) -> str:
        """The last `lines` of LinuxCNC's output."""
        try:
            text = self.log.read_text(errors="replace")
        except OSError:
            return "(no output)"
        return "\n".join(text.splitlines()[-lines:])

    def halcmd(self, *args: str, timeout_s: float = 60.0) -> str:
        """`halcmd ARGS` against this machine; its stdout, or SimError with its output."""
        done = subprocess.run(
            ["halcmd", *args],
            env=self.env,
            cwd=self.folder,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
        if done.returncode != 0:
            raise SimError(f"halcmd {' '.join(args)} failed ({done.returncode}): {(done.stdout + done.stderr).strip()}")
        return done.stdout

    def getp(self, pin: str) -> float | bool | int:
        """A pin's (or parameter's) value through `halcmd getp`, typed by `halcmd ptype`."""
        kind = self.halcmd("ptype", pin).strip()
        text = self.halcmd("getp", pin).strip()
        if kind == "bit":
            return text == "TRUE"
        if kind == "float":
            return float(text)
        return int(text)

    def stat(self) -> Any:
        """A fresh, polled `linuxcnc.stat()` of this machine (from compd.io.hal_modules' module); one
        made for an earlier Sim would read that one's shared memory."""
        _, linuxcnc = hal_modules.load()
        stat = linuxcnc.stat()
        stat.poll()
        return stat

    def run_program(self, path: Path | str, timeout_s: float = 60.0) -> None:
        """Ask the display to run the G-code file `path` in auto mode (returns once it was started)."""
        self._commands += 1
        number = self._commands
        tmp = self.folder / f"command-{number}.tmp"
        tmp.write_text(f"run {Path(path).resolve()}\n")
        tmp.rename(self.folder / f"command-{number}")
        reply = self.folder / f"reply-{number}"
        wait_for(
            lambda: reply.exists() or (self._proc is not None and self._proc.poll() is not None),
            f"the display's reply to `run {path}`",
            timeout_s,
        )
        if not reply.exists():
            raise SimError(f"linuxcnc exited while running {path}; its output ends:\n{self.tail()}")
        answer = reply.read_text().strip()
        if answer != "ok":
            raise SimError(f"run {path}: {answer}")

    # ---- stop

    def stop(self, timeout_s: float = 60.0) -> None:
        """Shut LinuxCNC down (the stop file, then signals to its group) and make sure nothing of it is left."""
        if self._proc is None and self._lock_fd is None:  # never started, or stopped already
            if not self.keep:
                shutil.rmtree(self.folder, ignore_errors=True)
            return
        began = time.monotonic()
        # LinuxCNC's shutdown (`halcmd unload all`) SIGTERMs the process of every userspace component:
        # one of this process's still loaded would end the test run. Ignored meanwhile, and a failure after.
        own = self._own_components() if self._proc is not None and self._proc.poll() is None else []
        shield = bool(own) and threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, signal.SIG_IGN) if shield else None
        try:
            if self._proc is not None:
                self._end_linuxcnc(timeout_s)
            self._clear_leftovers(timeout_s)
        finally:
            if shield:
                signal.signal(signal.SIGTERM, previous)
            if self._lock_fd is not None:
                os.close(self._lock_fd)  # releases the flock
                self._lock_fd = None
        self.stop_s = time.monotonic() - began
        if not self.keep:
            shutil.rmtree(self.folder, ignore_errors=True)
        if own:
            raise SimError(
                f"HAL component(s) of this process still loaded when the Sim stopped: {', '.join(own)} "
                f"(LinuxCNC's shutdown SIGTERMs their process): exit() them before the Sim stops"
            )

    def _own_components(self) -> list[str]:
        """This process's userspace HAL components (`halcmd show comp`: ID, User, name, PID, state)."""
        try:
            shown = self.halcmd("show", "comp", timeout_s=30.0)
        except (SimError, subprocess.TimeoutExpired):
            return []
        me = str(os.getpid())
        rows = (line.split() for line in shown.splitlines())
        return [row[2] for row in rows if len(row) >= 5 and row[1] == "User" and row[3] == me]

    def _end_linuxcnc(self, timeout_s: float) -> None:
        proc = self._proc
        assert proc is not None
        (self.folder / "stop").touch()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            # the group's SIGTERM ends the display (and milltask, io); `linuxcnc` then runs its Cleanup
            # (a SIGTERM to `linuxcnc` alone waits until its display has exited: bash defers the trap)
            _signal_group(proc.pid, signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                _signal_group(proc.pid, signal.SIGKILL)
                proc.wait()
        self._proc = None

    def _clear_leftovers(self, timeout_s: float) -> None:
        """What LinuxCNC's own shutdown left (only after a kill or a crash): processes, shm, /tmp files."""
        left = processes(None, with_token=self.token)
        if any(name == "rtapi_app" for _, name in left):
            subprocess.run(
                ["halrun", "-U"], env=self.env, cwd=self.folder, capture_output=True, timeout=60, check=False
            )
        for sig, wait_s in ((signal.SIGTERM, min(timeout_s, 20.0)), (signal.SIGKILL, 20.0)):
            left = processes(None, with_token=self.token)
            if not left:
                break
            for pid, _ in left:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, sig)
            end = time.monotonic() + wait_s
            while processes(None, with_token=self.token) and time.monotonic() < end:
                time.sleep(POLL_S)
        left = processes(None, with_token=self.token)
        if left:
            raise SimError(f"LinuxCNC's processes outlived SIGKILL: {_describe(left)}")
        if processes(LINUXCNC_PROGRAMS):
            return  # someone else's LinuxCNC (started since): its files and memory are not ours
        for key in shm_keys_left():
            subprocess.run(["ipcrm", "-M", hex(key)], capture_output=True, timeout=30, check=False)
        for name in sorted(linuxcnc_tmp_files() - self._tmp_before):
            path = Path("/tmp") / name
            with contextlib.suppress(OSError):
                if path.stat().st_size:  # a log of LinuxCNC's (killed before it removed it): kept beside ours
                    shutil.copyfile(path, self.folder / name)
                path.unlink()


def _signal_group(pgid: int, sig: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pgid, sig)


def processes(
    names: tuple[str, ...] | None, *, with_token: str | None = None, without: str | None = None
) -> list[tuple[int, str]]:
    """Live (not zombie) processes as (pid, name): named one of `names` (any when None), whose environment
    holds the Sim token `with_token`, or does not hold `without`."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                head, rest = fh.read().rsplit(")", 1)
            if rest.split()[0] == "Z":
                continue
            name = head.split("(", 1)[1]
            if names is not None and name not in names:
                continue
            if with_token is not None or without is not None:
                with open(f"/proc/{entry}/environ", "rb") as fh:
                    env = fh.read().split(b"\0")
                tokens = {e.split(b"=", 1)[1].decode() for e in env if e.startswith(TOKEN_VAR.encode() + b"=")}
                if with_token is not None and with_token not in tokens:
                    continue
                if without is not None and without in tokens:
                    continue
        except (OSError, IndexError, ValueError):
            continue  # gone meanwhile
        out.append((int(entry), name))
    return out


def _describe(procs: list[tuple[int, str]]) -> str:
    return ", ".join(f"{name} {pid}" for pid, name in procs)


def shm_keys_left() -> list[int]:
    """LinuxCNC's shared memory keys still present (`ipcrm` marks one that is still attached for removal
    at its last detach, as LinuxCNC's own shutdown does)."""
    out = []
    with open("/proc/sysvipc/shm") as fh:
        next(fh)
        for line in fh:
            fields = line.split()
            key = int(fields[0]) & 0xFFFFFFFF  # printed as a signed int
            if key in SHM_KEYS:
                out.append(key)
    return out


def linuxcnc_tmp_files() -> set[str]:
    """LinuxCNC's files in /tmp: its lock and its debug/print logs (linuxcnc.debug.XXXXXX, linuxcnc.print.XXXXXX)."""
    return {
        n for n in os.listdir("/tmp") if n == LINUXCNC_LOCK.name or n.startswith(("linuxcnc.debug.", "linuxcnc.print."))
    }

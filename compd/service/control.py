"""The probe socket: how `compd probe` hands a measurement to the running daemon.

The daemon (`ControlServer`, bound by compd/daemon/host.py when the config has an
`adapt` section) listens on a Unix domain socket; a thread of the service (a process
of its own on the wall clock) serves it through a `ProbeLink`: it hands the probe to
the cycle (a message ring the cycle reads between cycles: the cycle never waits) and
then watches the adapter's events that come back for that probe, at most `WAIT_S`,
so the answer can say whether the probe was accepted or rejected; if the cycle has
not taken it by then (the loop is paused for a reload) the answer is `queued`.

Where the socket is (`socket_path`): `adapt.socket_path` (relative to the config),
else the status file's path with the suffix `.sock` (status.json → status.sock), so
under systemd it is $RUNTIME_DIRECTORY/status.sock. The file is 0660 and removed at
shutdown; a stale one left by a crashed daemon refuses connections, which the client
reports as "no daemon" (exit 1) and the next daemon replaces.

Protocol: one JSON object on one line each way.
  request  {"op": "probe", "axis": "x", "error_um": 5.2, "position_mm": null,
            "sigma_um": null, "residual": false}
  answer   {"ok": true, "outcome": "accepted" | "rejected" | "queued" | ..., ...}
           {"ok": false, "error": "why"}   (a bad request: `compd probe` exits 2)

Every request gets an answer: one that is not JSON, longer than `MAX_REQUEST` bytes, nested
too deep for the parser, or holds a number no float can (an int of hundreds of digits) is
a bad request like any other; the probe's numbers are bounded as the adapter bounds them
(compd.cycle.adapt.probe_problem). The thread goes on serving whatever a client sends.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import socket
import stat
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any

from compd.core.errors import BadInput
from compd.core.probe import Probe, brief, finite_number, probe_problem
from compd.service.status import status_path
from compd.service.threads import ServiceThread

if TYPE_CHECKING:
    from compd.config import Config

log = logging.getLogger("compd.control")

WAIT_S = 2.0  # how long the server waits for the cycle to take a probe before answering "queued"
CLIENT_TIMEOUT_S = 5.0  # how long `compd probe` waits for the answer
MAX_REQUEST = 4096
SUN_PATH_MAX = 107  # bytes of a Unix socket path (sun_path is 108 with the NUL)
DEFAULT_PATH = "/run/compd/status.sock"


class NoDaemon(Exception):
    """Nothing answers on the socket: no file, a stale file, or no answer in time."""


def socket_path(cfg: Config, env: dict[str, str] | None = None) -> Path | None:
    """The probe socket of a config with an `adapt` section: `adapt.socket_path`, else next
    to the status file (its suffix replaced by `.sock`); None without either."""
    ad = cfg.top.adapt
    tel = cfg.top.telemetry
    if ad is None and (tel is None or not tel.remote_models.allow):
        return None
    if ad is not None and ad.socket_path:
        return cfg.resolve_path(ad.socket_path)
    status = status_path(cfg, env)
    return None if status is None else sock_beside(status)


def socket_key(cfg: Config) -> tuple[str, ...]:
    """The config key the probe socket's path comes from: `adapt.socket_path`, else `status.path`
    (the socket lies beside the status file; under systemd beside $RUNTIME_DIRECTORY/status.json)."""
    ad = cfg.top.adapt
    return ("adapt", "socket_path") if ad is not None and ad.socket_path else ("status", "path")


def unbindable(path: Path) -> str | None:
    """Why a Unix socket cannot be bound at `path` by this user (None: it can): longer than
    sun_path holds, its folder missing or not writable, or a file there that is not a socket."""
    n = len(os.fsencode(path))
    if n > SUN_PATH_MAX:
        return f"the probe socket {path} is {n} bytes long: a Unix socket path is at most {SUN_PATH_MAX}"
    folder = path.parent
    if not folder.is_dir():
        return f"the folder {folder} of the probe socket {path} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"the probe socket {path} cannot be made: its folder is not writable (uid {os.geteuid()})"
    try:
        mode = path.lstat().st_mode
    except OSError:
        return None
    return None if stat.S_ISSOCK(mode) else f"{path} exists and is not a socket"


def check_socket_path(cfg: Config, env: dict[str, str] | None = None) -> None:
    """A config error naming the key (`socket_key`) when the probe socket of `cfg` cannot be
    bound where it would be (`unbindable`): what `compd check-config` accepts, `compd run` binds."""
    path = socket_path(cfg, env)
    why = None if path is None else unbindable(path)
    if why is not None:
        raise cfg.doc.error(why, socket_key(cfg))


def sock_beside(status: Path) -> Path:
    """status.json → status.sock (a status file already named .sock gets .sock appended)."""
    p = Path(status).with_suffix(".sock")
    return p if p != Path(status) else Path(f"{status}.sock")


def check_request(req: Any, axes: list[str]) -> str | None:
    """Why a probe request is bad, or None."""
    if not isinstance(req, dict) or req.get("op") != "probe":
        return "not a probe request"
    axis = req.get("axis")
    if not isinstance(axis, str) or axis not in axes:
        return f"unknown axis {brief(axis)}: the daemon adapts {', '.join(axes)}"
    bad = probe_problem(req.get("error_um"), req.get("sigma_um"), req.get("position_mm"))
    if bad is not None:
        return f"{bad[0]} {bad[1]}"
    if not isinstance(req.get("residual", False), bool):
        return "residual must be true or false"
    return None


class ProbeLink(ABC):
    """What the probe socket's thread reaches of the running pipeline."""

    @property
    @abstractmethod
    def axes(self) -> list[str] | None:
        """The axes the adapter estimates (None: no adapter)."""

    @abstractmethod
    def send(self, probe: Probe) -> None:
        """Hand `probe` to the cycle (never waits on it); a NaN `t_s` is stamped by the cycle."""

    @abstractmethod
    def outcome(self, tag: str) -> dict[str, Any] | None:
        """The adapter's newest event for the probe sent with source `tag`, or None yet."""

    def arm_model(self, window_s: float | None) -> dict[str, Any]:
        """`compd arm-model`: arm the remote model handler; the answer (a pipeline without one refuses)."""
        return {"ok": False, "error": "this daemon takes no remote models (telemetry.remote_models.allow)"}


class ControlServer:
    """The daemon's end of the probe socket: bound by the daemon (`open`), served one request
    at a time by a thread of the service (`serve`)."""

    def __init__(self, path: Path, key: tuple[str, ...] = ("adapt", "socket_path")) -> None:
        self.path = Path(path)
        self.key = key  # the config key the path comes from (`socket_key`), for the error
        self.daemon_pid = os.getpid()  # the daemon's, also when a service process serves the socket
        self.link: ProbeLink | None = None  # the running pipeline's (a reload points it at the new one)
        self.served = 0
        self._sock: socket.socket | None = None
        self._ino: int | None = None
        self._n = 0
        self._stop = threading.Event()
        self._thread: ServiceThread | None = None

    # ------------------------------------------------------------------ life
    def open(self) -> None:
        """Bind (0660), replacing a stale socket file; BadInput if another daemon serves it."""
        path = self.path
        why = unbindable(path)
        if why is not None:
            raise BadInput(why, path=self.key)
        if path.is_socket():
            if _answers(path):
                raise BadInput(f"another compd serves {path}", path=self.key)
            path.unlink()  # a crashed daemon's socket
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(path))
            os.chmod(path, 0o660)  # before listen(): no one can connect earlier
            sock.listen(8)
            sock.settimeout(0.2)
            self._ino = path.stat().st_ino
        except OSError as e:
            sock.close()
            raise BadInput(f"cannot open the probe socket {path}: {e.strerror or e}", path=self.key) from None
        self._sock = sock
        log.info("probe socket %s", path, extra={"event": "probe_socket", "path": str(path)})

    def fileno(self) -> int | None:
        """The listening socket (a service process keeps it open), or None when not bound."""
        return self._sock.fileno() if self._sock is not None else None

    def serve(self, link: ProbeLink) -> None:
        """Answer requests from a thread of this process, through `link`."""
        self.link = link
        if self._sock is None or self._thread is not None:
            return
        self._stop.clear()
        self._thread = ServiceThread("compd-control", self._run)
        self._thread.start()

    def stop_serving(self) -> None:
        """End this process's serving thread; the socket stays bound (another takes over)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def close(self) -> None:
        """Stop serving and remove the socket file (unless another daemon has replaced it)."""
        self.stop_serving()
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            with contextlib.suppress(OSError):
                if self.path.stat().st_ino == self._ino:
                    self.path.unlink()

    # ------------------------------------------------------------- the thread
    def _run(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                try:
                    self._serve(conn)
                except OSError:  # a client that hangs up or stalls never stops the thread
                    log.debug("probe request failed", exc_info=True, extra={"event": "probe_request_error"})
                except Exception:  # a bug: said loudly, and the next request is served all the same
                    log.error("probe request failed", exc_info=True, extra={"event": "probe_request_error"})

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(WAIT_S)
        data = b""
        while b"\n" not in data and len(data) < MAX_REQUEST:
            chunk = conn.recv(MAX_REQUEST)
            if not chunk:
                break
            data += chunk
        answer: dict[str, Any]
        if b"\n" not in data and len(data) >= MAX_REQUEST:
            answer = {"ok": False, "error": f"a request is one line of at most {MAX_REQUEST} bytes"}
        else:
            try:
                req = json.loads(data.split(b"\n", 1)[0].decode("utf-8"))
            except RecursionError:
                answer = {"ok": False, "error": "not a JSON request: nested too deep"}
            except (UnicodeDecodeError, ValueError) as e:  # not UTF-8, not JSON
                answer = {"ok": False, "error": f"not a JSON request: {e}"}
            else:
                answer = self.handle(req)
        conn.sendall((json.dumps(answer) + "\n").encode("utf-8"))
        self.served += 1

    def handle(self, req: Any) -> dict[str, Any]:
        """Send one probe to the cycle and wait (bounded) for its verdict on it; or arm the
        remote model handler (`{"op": "arm_model", "window_s": null}`)."""
        link = self.link
        if isinstance(req, dict) and req.get("op") == "arm_model":
            if link is None:
                return {"ok": False, "error": "the daemon is starting"}
            w = req.get("window_s")
            if w is not None and not finite_number(w):
                return {"ok": False, "error": f"window_s must be a finite number, got {brief(w)}"}
            return link.arm_model(w)
        if link is None or link.axes is None:
            return {"ok": False, "error": "this daemon has no adapt section"}
        try:
            why = check_request(req, link.axes)
        except (TypeError, ValueError, OverflowError) as e:  # a value no check foresaw: refused, never unanswered
            why = f"bad request: {type(e).__name__}: {e}"
        if why is not None:
            return {"ok": False, "error": why}
        self._n += 1
        tag = f"cli#{self._n}@{os.getpid()}"
        probe = Probe(
            t_s=math.nan,
            axis=req["axis"],
            error_um=float(req["error_um"]),
            sigma_um=None if req.get("sigma_um") is None else float(req["sigma_um"]),
            position_mm=None if req.get("position_mm") is None else float(req["position_mm"]),
            source=tag,
            residual=bool(req.get("residual", False)),
        )
        link.send(probe)
        answer: dict[str, Any] = {
            "ok": True,
            "outcome": "queued",
            "axis": probe.axis,
            "t_s": None,
            "pid": self.daemon_pid,
        }
        deadline = time.monotonic() + WAIT_S
        while not self._stop.is_set() and time.monotonic() < deadline:
            ev = link.outcome(tag)
            if ev is not None:
                answer.update({k: v for k, v in ev.items() if k not in ("source", "event")})
                answer["outcome"] = ev["event"]
                return _jsonable(answer)
            self._stop.wait(0.01)
        return answer


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def _answers(path: Path) -> bool:
    """True if a daemon accepts connections on `path`."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(1.0)
    try:
        s.connect(str(path))
    except OSError:
        return False
    finally:
        s.close()
    return True


def send_probe(path: Path | str, request: dict[str, Any], timeout_s: float = CLIENT_TIMEOUT_S) -> dict[str, Any]:
    """Send one request, return the daemon's answer; NoDaemon when nothing answers."""
    path = str(path)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        try:
            s.connect(path)
        except FileNotFoundError:
            raise NoDaemon(f"no compd running: no probe socket {path}") from None
        except ConnectionRefusedError:
            raise NoDaemon(f"no compd running: {path} refuses connections (left by a daemon that stopped)") from None
        except OSError as e:
            raise NoDaemon(f"cannot reach compd at {path}: {e.strerror or e}") from None
        try:
            s.sendall((json.dumps(request) + "\n").encode("utf-8"))
            data = b""
            while b"\n" not in data:
                chunk = s.recv(MAX_REQUEST)
                if not chunk:
                    break
                data += chunk
        except TimeoutError:
            raise NoDaemon(f"compd at {path} did not answer within {timeout_s:g} s") from None
        except OSError as e:
            raise NoDaemon(f"compd at {path} hung up: {e.strerror or e}") from None
    finally:
        s.close()
    try:
        answer = json.loads(data.split(b"\n", 1)[0].decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise NoDaemon(f"{path}: the answer is not compd's") from None
    if not isinstance(answer, dict):
        raise NoDaemon(f"{path}: the answer is not compd's")
    return answer

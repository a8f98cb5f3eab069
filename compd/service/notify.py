"""systemd notify protocol (sd_notify): READY, WATCHDOG, STOPPING and STATUS over $NOTIFY_SOCKET.

No dependency: a datagram of `KEY=VALUE` lines sent to the unix socket named by
$NOTIFY_SOCKET (a leading '@' names a socket in the abstract namespace). The
watchdog is pinged from the cycle itself (`WatchdogObserver`), at half the
interval systemd asks for in $WATCHDOG_USEC, so a hung loop — not merely a live
process — is what systemd detects.
"""

from __future__ import annotations

import math
import os
import socket
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from compd.io.ring import SharedBlob

if TYPE_CHECKING:
    from compd.cycle.loop import Loop


def socket_address(value: str) -> str:
    """$NOTIFY_SOCKET as a socket address: '@name' → '\\0name' (abstract namespace)."""
    return "\0" + value[1:] if value.startswith("@") else value


def watchdog_interval_s(env: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """The watchdog timeout systemd set ($WATCHDOG_USEC, s), or None.

    None too when $WATCHDOG_PID names another process (the watchdog is not ours).
    """
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    want_pid = env.get("WATCHDOG_PID")
    if want_pid and want_pid.strip() != str(os.getpid() if pid is None else pid):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


class Notifier:
    """Sends notify messages; every error is swallowed (no notify socket must ever stop compd)."""

    def __init__(self, address: str) -> None:
        self.address = socket_address(address)
        self.sock: socket.socket | None = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sent = 0
        self.errors = 0

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Notifier | None:
        """A notifier for $NOTIFY_SOCKET, or None when compd is not run by systemd."""
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET")
        return cls(address) if address else None

    def send(self, **fields: Any) -> bool:
        """Send `KEY=value` lines, e.g. send(READY=1, STATUS="running"); True if sent."""
        if self.sock is None:
            return False
        text = "\n".join(f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items())
        try:
            self.sock.sendto(text.encode("utf-8"), self.address)
        except OSError:
            self.errors += 1
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class WatchdogObserver:
    """A loop observer: READY=1 after the first cycle, then WATCHDOG=1 every `interval_s`,
    and STATUS= whenever the line in `status_line` (written by the service) changed,
    checked every `status_every_s`.

    Per cycle it reads the monotonic clock and compares it with a deadline; it
    sends something only on the first cycle, once per interval and when the status
    line changed.
    """

    def __init__(
        self,
        notifier: Notifier,
        watchdog_s: float | None,
        status: str = "running",
        clock: Callable[[], float] = time.monotonic,
        status_line: SharedBlob | None = None,
        status_every_s: float = 1.0,
        healthy: Callable[[], bool] | None = None,
    ) -> None:
        self.notifier = notifier
        self.clock = clock
        self.interval_s = watchdog_s / 2 if watchdog_s else math.inf
        self.status = status
        self.status_line = status_line
        self.status_every_s = status_every_s
        self.ready = False
        self.pings = 0
        self._next_s = -math.inf
        self._next_status_s = math.inf if status_line is None else -math.inf
        self._line_version = 0
        self.healthy = healthy  # False: the supervisor gave up on a child; no more pings
        self.starved = False

    def ping(self) -> None:
        """WATCHDOG=1 now, outside a cycle: the daemon pauses its loop on purpose (a reload builds
        the new pipeline), and the new pipeline's first cycle pings again."""
        if math.isfinite(self.interval_s) and self.ready and (self.healthy is None or self.healthy()):
            self.notifier.send(WATCHDOG=1)
            self.pings += 1

    def __call__(self, loop: Loop, now_s: float) -> None:
        t = self.clock()
        if t >= self._next_status_s and self.ready:
            self._next_status_s = t + self.status_every_s
            assert self.status_line is not None
            if self.status_line.version != self._line_version:
                self._line_version = self.status_line.version
                line = self.status_line.read()
                if line:
                    self.notifier.send(STATUS=line.decode("utf-8", "replace"))
        if t < self._next_s:
            return
        self._next_s = t + self.interval_s
        if not self.ready:
            self.ready = True
            if math.isfinite(self.interval_s) and (self.healthy is None or self.healthy()):
                # the first cycle pings too: after a reload the interval starts anew here, so the
                # gap between two pings is never the old pipeline's interval plus the new one's
                self.notifier.send(READY=1, STATUS=self.status, WATCHDOG=1)
                self.pings += 1
            else:
                self.notifier.send(READY=1, STATUS=self.status)
        elif self.healthy is None or self.healthy():
            self.notifier.send(WATCHDOG=1)
            self.pings += 1
        elif not self.starved:
            self.starved = True
            self.notifier.send(STATUS="I/O processes keep dying: watchdog no longer fed")

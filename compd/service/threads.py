"""The one thread base of the service's threads: named, started once, joined with a deadline, and never dying silently.

The service (compd/daemon/host.py) runs its work on threads of its own process: the message
taker (`compd-service`), the data log's writer (`compd-log`), the state file's writer
(`compd-state`), the probe socket (`compd-control`), the metrics endpoint
(`compd-metrics`), the MQTT client (`compd-telemetry`) and the OPC UA server
(`compd-opcua`). Each is a `ServiceThread`: what its owner gives is the function the
thread runs; the base owns the rest, the same for all of them:

* the name (what `compd status`, `top -H` and a bench's activity trace show);
* an exception that escapes the function is logged once, with its traceback (event
  `service_thread_failed`, the thread's name), and the thread ends: the owner sees it
  as not `alive` (the telemetry then keeps nothing in memory) — never a silent death;
* `join(timeout_s)`: False, with one warning (`service_thread_stuck`), when it has not
  ended by then (it is a daemon thread: it never holds the process up at exit).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger("compd.service")


class ServiceThread:
    """A thread of the service running `run(*args)` (see the module)."""

    def __init__(self, name: str, run: Callable[..., Any], *args: Any) -> None:
        self.name = name
        self._run = run
        self._args = args
        self.failure: str | None = None  # the exception that ended it, as text
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def is_current(self) -> bool:
        """Whether this is the thread calling (an owner stopping itself from its own thread)."""
        return self._thread is threading.current_thread()

    def join(self, timeout_s: float) -> bool:
        """Wait up to `timeout_s` for the thread to end; False (logged once) when it has not."""
        if not self._thread.is_alive() or self.is_current():
            return not self._thread.is_alive()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning(
                "service thread %s did not stop within %g s",
                self.name,
                timeout_s,
                extra={"event": "service_thread_stuck", "service_thread": self.name},
            )
            return False
        return True

    def _main(self) -> None:
        try:
            self._run(*self._args)
        except Exception as e:
            self.failure = f"{type(e).__name__}: {e}"
            log.exception(
                "service thread %s failed: %s",
                self.name,
                self.failure,
                extra={"event": "service_thread_failed", "service_thread": self.name, "reason": self.failure},
            )

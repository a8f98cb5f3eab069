"""The life cycle a device with its own thread shares: open the line, run, stop, close."""

from __future__ import annotations

import threading
from typing import Any


class DeviceThread:
    """Base of devices that run on a thread of their own (DCON module, CAN broadcaster, CNC scans).

    Subclasses implement `_run()` (loop until `self._stop` is set) and, when they hold
    a line (the serial port, the bus), `_open()` and `_close()`; `start`/`stop` and the
    context manager are here.
    """

    thread_name = "device"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _open(self) -> None:
        """Before the thread starts (nothing by default)."""

    def _run(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        """After the thread has stopped (nothing by default)."""

    def start(self) -> Any:
        self._open()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        self._close()

    def __enter__(self) -> Any:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

"""A Modbus TCP link for sinks: writes from the cycle are queued, a thread does the I/O.

The cycle never waits on the network: `submit` stores the newest values per
register range, the link's thread writes them (in order of first submission) and
reads a status block every `status_period_s`. A lost connection is retried with
exponential back-off; what the sink knows of the device is the last status read.
Every read-back is shape-checked (`compd.modbus_reply`: function code, register count,
frame length, unit): a reply of the wrong shape is a link error (`errors`, `bad_replies`,
`last_error`), never taken as the device's status or applied value.
`state` is the link as the thread last found it: connecting (started, no answer
yet), up, down (connect or I/O failed), closed.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from compd.histogram import DurationHist
from compd.modbus_reply import HOLDING, FrameTap, shape_error


class ModbusLink:
    """Holding-register writes and a status read on a background thread."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        device_id: int = 1,
        timeout_s: float = 0.25,
        status: tuple[int, int] | None = None,
        status_period_s: float = 0.05,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 5.0,
        name: str = "sink",
    ) -> None:
        self.host, self.port, self.device_id = host, port, device_id
        self.timeout_s = timeout_s
        self.status_range = status
        self.status_period_s = status_period_s
        self.reconnect_min_s, self.reconnect_max_s = reconnect_min_s, reconnect_max_s
        self.status: list[int] | None = None
        self.status_stamp = -1.0
        self.state = "closed"
        self.writes = 0
        self.errors = 0
        self.bad_replies = 0
        self.last_error: str | None = None
        self.name = name
        self._tap = FrameTap()
        self.write_hist = DurationHist()  # request to reply of each write, µs
        self.latency_hist = DurationHist()  # queued by the cycle to acknowledged by the device, µs
        self._pending: dict[int, tuple[list[int], int]] = {}  # address -> (values, queued at, ns)
        self._inflight = False  # a write taken from _pending, not yet acknowledged (or put back)
        self._cv = threading.Condition()
        self._io = threading.Lock()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._client: Any = None

    def start(self) -> None:
        from pymodbus.client import ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        self._client = ModbusTcpClient(
            self.host, port=self.port, timeout=self.timeout_s, retries=0, trace_packet=self._tap
        )
        self._stop = False
        self.state = "connecting"
        self._thread = threading.Thread(target=self._run, name=f"modbus-link-{self.name}", daemon=True)
        self._thread.start()

    def submit(self, address: int, values: list[int]) -> None:
        """Queue a write; a newer write to the same address replaces an unsent one."""
        with self._cv:
            self._pending[address] = ([v & 0xFFFF for v in values], time.perf_counter_ns())
            self._cv.notify()

    def pending(self) -> bool:
        """Whether a write is queued or on its way (not yet acknowledged by the device)."""
        with self._cv:
            return bool(self._pending) or self._inflight

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until every queued write has been acknowledged by the device, or has failed
        and is queued again (or `timeout_s`)."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._pending or self._inflight:
                rest = deadline - time.monotonic()
                if rest <= 0:
                    return False
                self._cv.wait(rest)
        return True

    def read_now(self, address: int, count: int) -> list[int] | None:
        """A synchronous read from the caller's thread (tests, settle); None on error."""
        with self._io:
            return self._read(address, count)

    def _read(self, address: int, count: int) -> list[int] | None:
        try:
            if not self._client.connected and not self._client.connect():
                return None
            rr = self._client.read_holding_registers(address, count=count, device_id=self.device_id)
        except Exception as e:
            self._fail(e)
            return None
        if rr.isError():
            self.errors += 1
            self.last_error = f"exception reply {getattr(rr, 'exception_code', '?')}"
            return None
        problem = shape_error(rr, HOLDING, count, self.device_id) or self._tap.tcp_error(
            getattr(rr, "transaction_id", 0), count
        )
        if problem is not None:
            self.errors += 1
            self.bad_replies += 1
            self.last_error = f"malformed reply to registers {address}+{count}: {problem}"
            return None
        return list(rr.registers)

    def _send(self, item: tuple[int, list[int]], queued_ns: int) -> bool:
        """One write (holding `_io`); False when the connection failed (the write is lost)."""
        try:
            w0 = time.perf_counter_ns()
            rr = self._client.write_registers(item[0], item[1], device_id=self.device_id)
            w1 = time.perf_counter_ns()
        except Exception as e:
            self._fail(e)
            return False
        self.write_hist.add_ns(w1 - w0)
        self.latency_hist.add_ns(w1 - queued_ns)
        if rr.isError():
            self.errors += 1
            self.last_error = f"write exception reply {getattr(rr, 'exception_code', '?')}"
        else:
            self.writes += 1
        return True

    def drain(self, timeout_s: float) -> bool:
        """Send what is queued on the caller's thread and wait for a write in flight: on
        return every write so far has been acknowledged by the device (lockstep runs,
        between two cycles). A failed write is queued again and retried until `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._cv:
                while self._inflight:
                    rest = deadline - time.monotonic()
                    if rest <= 0:
                        return False
                    self._cv.wait(rest)
                if not self._pending:
                    return True
                address = next(iter(self._pending))
                values, queued_ns = self._pending.pop(address)
                self._inflight = True
            with self._io:
                try:
                    ok = self._client.connected or bool(self._client.connect())
                except Exception as e:
                    ok = False
                    self.last_error = str(e)
                ok = ok and self._send((address, values), queued_ns)
            with self._cv:
                if not ok:
                    self._pending.setdefault(address, (values, queued_ns))
                self._inflight = False
                self._cv.notify_all()
            if not ok:
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.01)

    def _fail(self, e: Exception) -> None:
        self.state = "down"
        self.errors += 1
        self.last_error = f"{type(e).__name__}: {e}"
        self._client.close()

    def _run(self) -> None:
        backoff = self.reconnect_min_s
        next_status = 0.0
        while True:
            with self._cv:
                if (not self._pending or self._inflight) and not self._stop:
                    self._cv.wait(max(0.0, min(self.status_period_s, next_status - time.monotonic())))
                if self._stop and not self._pending:
                    break
                item = None
                took = False
                if self._pending and not self._inflight:  # not while drain() has one out
                    took = True
                    address = next(iter(self._pending))
                    values, queued_ns = self._pending.pop(address)
                    item = (address, values)
                    self._inflight = True
            with self._io:  # network I/O without holding the cycle's lock
                try:
                    ok = self._client.connected or bool(self._client.connect())
                except Exception as e:
                    ok = False
                    self.last_error = str(e)
                if ok and item is not None:
                    ok = self._send(item, queued_ns)
                    if ok:
                        item = None
                now = time.monotonic()
                if ok and self.status_range is not None and now >= next_status:
                    regs = self._read(*self.status_range)
                    if regs is not None:
                        self.status = regs
                        self.status_stamp = now
                    next_status = now + self.status_period_s
                if ok and self._client.connected:
                    self.state = "up"
            if took:
                with self._cv:
                    if item is not None:
                        self._pending.setdefault(item[0], (item[1], queued_ns))  # unless superseded meanwhile
                        item = None
                    self._inflight = False
                    self._cv.notify_all()
            if not ok:
                self.state = "down"
                self.errors += 1
                with self._cv:
                    if self._stop:
                        break
                    self._cv.wait(backoff)
                backoff = min(backoff * 2, self.reconnect_max_s)
            else:
                backoff = self.reconnect_min_s

    def get_status(self) -> dict[str, Any]:
        return {"state": self.state, "writes": self.writes, "errors": self.errors, "bad_replies": self.bad_replies,
                "last_error": self.last_error}

    def stop(self, timeout_s: float = 2.0) -> None:
        """Send what is queued (up to `timeout_s`), then close."""
        if self._thread is not None:
            self.flush(timeout_s)
            with self._cv:
                self._stop = True
                self._pending.clear()
                self._cv.notify()
            self._thread.join(5)
            self._thread = None
        if self._client is not None:
            self._client.close()
        self.state = "closed"

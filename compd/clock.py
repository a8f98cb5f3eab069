"""Clocks injected into the loop: wall time (sleep then spin), simulated time, or a plant's clock over
Modbus, followed in real time or in lockstep."""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import Any

from compd.modbus_reply import HOLDING, shape_error

READ_WRITE = 0x17  # Modbus function 23, read/write multiple registers


class Clock(ABC):
    """What the loop needs of a clock: the time now (s), a wait until a deadline, and
    `start`/`stop` around a run (a clock read from elsewhere connects there).

    `simulated` is True when the clock's time is not wall time (the loop then keeps
    the interpreter's thread switch interval as it is, and no real-time option applies).
    """

    simulated: bool = False

    @abstractmethod
    def now(self) -> float:
        """Loop time, s."""

    def bind(self, sink: Any, sources: list[Any]) -> None:
        """The pipeline's sink and sources, for a clock that drives their I/O between cycles
        (a lockstep plant clock); others ignore them."""

    def adopt_poller(self, source: Any) -> bool:
        """A polled source asks whether the clock drives its polls (a lockstep plant clock
        polls every source once per cycle at the plant time). False: it polls on its own
        thread."""
        return False

    @abstractmethod
    def wait_until(self, deadline_s: float) -> None:
        """Return at (or as soon as possible after) loop time `deadline_s`."""

    def start(self) -> None:
        """Called once before the loop opens anything (a clock read from elsewhere connects)."""

    def stop(self) -> None:
        """Release what `start` took; called after the loop closed."""


class WallClock(Clock):
    """Monotonic wall time. `wait_until` sleeps until `spin_margin_s` before the
    deadline, then spins, which cuts lateness from ~0.1 ms to a few µs."""

    simulated = False

    def __init__(self, spin_margin_s: float = 0.0002) -> None:
        self.spin_margin_s = spin_margin_s

    def now(self) -> float:
        return time.monotonic()

    def wait_until(self, deadline_s: float) -> None:
        rest = deadline_s - time.monotonic() - self.spin_margin_s
        if rest > 0:
            time.sleep(rest)
        while time.monotonic() < deadline_s:
            pass


class SimClock(Clock):
    """Simulated time: `wait_until` jumps to the deadline at once.

    With `speedup` > 0 the clock also paces itself against wall time, so that
    `speedup` simulated seconds pass per wall second (the demo uses that).
    """

    simulated = True

    def __init__(self, start_s: float = 0.0, speedup: float = 0.0) -> None:
        self.t_s = float(start_s)
        self.speedup = speedup
        self._wall0 = time.monotonic()
        self._sim0 = self.t_s

    def now(self) -> float:
        return self.t_s

    def wait_until(self, deadline_s: float) -> None:
        if deadline_s > self.t_s:
            self.t_s = deadline_s
        if self.speedup > 0:
            wall_due = self._wall0 + (self.t_s - self._sim0) / self.speedup
            rest = wall_due - time.monotonic()
            if rest > 0:
                time.sleep(rest)

    def set(self, t_s: float) -> None:
        """Jump (replay: to the next row's time)."""
        self.t_s = t_s


class PlantClock(Clock):
    """The plant's own clock, read over Modbus TCP (a simulator running faster than wall time).

    A thread polls two holding registers (plant time in ms, uint32, high word first,
    hil_sim's `plant` device map) every `poll_period_s` of wall time; `now()` is the
    last plant time read, so everything on the loop clock — AR(1)'s Δτ, the guard's
    slew and staleness, the sinks' update intervals, the sources' time stamps — runs
    in plant seconds. `wait_until` sleeps until the plant reaches the deadline; if the
    plant time stops advancing for `stall_s` of wall time it returns anyway, so the
    loop can still see a stop request; if the plant has not answered for `lost_s` it
    raises RuntimeError (the run ends with the safe output: a simulation without its
    plant has nothing left to follow).
    """

    simulated = False

    def __init__(
        self,
        host: str,
        port: int,
        *,
        device_id: int = 1,
        address: int = 0,
        poll_period_s: float = 0.001,
        stall_s: float = 0.5,
        timeout_s: float = 0.5,
        lost_s: float = 5.0,
    ) -> None:
        self.host, self.port, self.device_id, self.address = host, port, device_id, address
        self.poll_period_s = poll_period_s
        self.stall_s = stall_s
        self.timeout_s = timeout_s
        self.lost_s = lost_s
        self._ok_wall = time.monotonic()
        self.t_s = 0.0
        self.reads = 0
        self.errors = 0
        self._changed_wall = time.monotonic()
        self._client: object | None = None
        self._thread: object | None = None
        self._stop = False

    def _read(self) -> float | None:
        client: Any = self._client
        try:
            if not client.connected and not client.connect():
                return None
            rr = client.read_holding_registers(self.address, count=2, device_id=self.device_id)
        except Exception:
            client.close()
            return None
        if rr.isError() or shape_error(rr, HOLDING, 2, self.device_id) is not None:
            return None
        hi, lo = rr.registers
        return ((hi << 16) | lo) / 1000.0

    def start(self) -> None:
        """Connect and read the plant time once (RuntimeError if the plant does not answer)."""
        import logging
        import threading

        from pymodbus.client import ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        self._client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        deadline = time.monotonic() + 5.0
        t = self._read()
        while t is None and time.monotonic() < deadline:
            time.sleep(0.05)
            t = self._read()
        if t is None:
            self._client.close()  # type: ignore[attr-defined]
            raise RuntimeError(f"plant clock: no answer from {self.host}:{self.port}")
        self.t_s = t
        self._changed_wall = self._ok_wall = time.monotonic()
        self._stop = False
        th = threading.Thread(target=self._run, name="plant-clock", daemon=True)
        self._thread = th
        th.start()

    def _run(self) -> None:
        while not self._stop:
            t = self._read()
            if t is None:
                self.errors += 1
            else:
                self.reads += 1
                self._ok_wall = time.monotonic()
                if t > self.t_s:
                    self.t_s = t
                    self._changed_wall = time.monotonic()
            time.sleep(self.poll_period_s)

    def stop(self) -> None:
        self._stop = True
        th: Any = self._thread
        if th is not None:
            th.join(2.0)
            self._thread = None
        if self._client is not None:
            self._client.close()  # type: ignore[attr-defined]
            self._client = None

    def now(self) -> float:
        return self.t_s

    def wait_until(self, deadline_s: float) -> None:
        while self.t_s < deadline_s:
            now = time.monotonic()
            if now - self._ok_wall > self.lost_s:
                raise RuntimeError(f"plant clock: no answer from {self.host}:{self.port} for {self.lost_s:g} s")
            if now - self._changed_wall > self.stall_s:
                return
            time.sleep(self.poll_period_s * 0.5)


class LockstepPlantClock(PlantClock):
    """A plant that waits for compd (hil_sim `plant` device with `lockstep`): test runs that
    give the same result however busy the machine is.

    No thread follows the plant. `wait_until(deadline)` runs between two cycles: it waits
    until the sink's writes have been acknowledged by the device (`Sink.flush`), writes
    the deadline to the plant's run-to registers and reads the plant time back in the
    same request (Modbus function 23: the plant steps its physics and its CNC up to the
    deadline before it answers), then polls every polled source once on this thread,
    stamped with that time (`PolledSource.poll_now`; their own threads are not started). So the cycle at plant time t
    sees the plant's signals at t, and the plant sees the output of every cycle before
    t. Every wait is for a reply, never for wall time: a request that fails is retried
    until `lost_s` (60 s) of wall time without an answer, and a source whose device did
    not answer is polled again, so a stall changes how long a run takes, not its result.
    """


    def __init__(self, host: str, port: int, *, device_id: int = 1, address: int = 0, lost_s: float = 60.0) -> None:
        super().__init__(host, port, device_id=device_id, address=address, timeout_s=lost_s, lost_s=lost_s)
        self.sink: Any = None
        self.sources: list[Any] = []
        self.finished = False
        self.releases = 0

    def adopt_poller(self, source: Any) -> bool:
        """A polled source this clock polls between cycles (instead of its own thread)."""
        if not any(source is s for s in self.sources):
            self.sources.append(source)
        return True

    def bind(self, sink: Any, sources: list[Any]) -> None:
        """The sink whose writes a release waits for; the sources still polled (after a reload)."""
        self.sink = sink
        self.sources = [s for s in self.sources if any(s is x for x in sources)]

    def start(self) -> None:
        import logging

        from pymodbus.client import ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        self._client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        self.t_s = self._answer(self._read, "no answer")

    def stop(self) -> None:
        self.sources = []
        if self._client is not None:
            self._client.close()  # type: ignore[attr-defined]
            self._client = None

    def _answer(self, request: Any, what: str) -> Any:
        """`request()` until it answers (not None), or RuntimeError after `lost_s` of wall time."""
        deadline = time.monotonic() + self.lost_s
        while True:
            r = request()
            if r is not None:
                self.reads += 1
                return r
            self.errors += 1
            if time.monotonic() > deadline:
                raise RuntimeError(f"plant clock (lockstep): {what} from {self.host}:{self.port} for {self.lost_s:g} s")
            time.sleep(0.01)

    def _run_to(self, t_s: float) -> tuple[float, int] | None:
        """One Modbus request (function 23, write then read): run to `t_s` — the plant steps
        before it acknowledges — and read back (plant time, state); None on no answer."""
        client: Any = self._client
        ms = int(round(t_s * 1000.0)) & 0xFFFFFFFF
        try:
            if not client.connected and not client.connect():
                return None
            rr = client.readwrite_registers(
                read_address=self.address, read_count=3, write_address=self.address + 4,
                values=[(ms >> 16) & 0xFFFF, ms & 0xFFFF], device_id=self.device_id,
            )
        except Exception:
            client.close()
            return None
        if rr.isError() or shape_error(rr, READ_WRITE, 3, self.device_id) is not None:
            return None
        hi, lo, state = rr.registers
        return ((hi << 16) | lo) / 1000.0, state

    def wait_until(self, deadline_s: float) -> None:
        if self.sink is not None and not self.sink.flush(self.lost_s):
            raise RuntimeError(f"lockstep: the sink's writes were not acknowledged within {self.lost_s:g} s")
        t, state = self._answer(lambda: self._run_to(deadline_s), "no acknowledgement of the run-to time")
        self.releases += 1
        self.t_s = max(self.t_s, t)
        self.finished = state == 2
        for s in self.sources:
            stamp = self.t_s
            self._answer(lambda s=s, stamp=stamp: True if s.poll_now(stamp) else None, f"source {s.name}: no answer")

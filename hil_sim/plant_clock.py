"""The clock of a simulated plant, read over Modbus from its clock device, followed in real time or in lockstep.

It is compd's `loop.clock: plant` (entry point `compd.clocks`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from compd.core.clock import Clock, DrivenSink, DrivenSource
from compd.core.config import PlantClockConfig
from compd.io.mailbox import Latest
from compd.io.modbus_client import LinkFault, ModbusClient, ModbusFault, OverModbus
from compd.io.worker import DeviceWork, IoWorker, LinkDown


def from_config(pc: PlantClockConfig) -> Clock:
    """The clock `loop.plant_clock` describes: in lockstep with the plant, or following it."""
    if pc.lockstep:
        return LockstepPlantClock(pc.host, pc.port, device_id=pc.device_id, address=pc.address)
    return PlantClock(
        pc.host, pc.port, device_id=pc.device_id, address=pc.address, poll_period_s=pc.poll_period_s, stall_s=pc.stall_s
    )


class PlantTimeWork(OverModbus, DeviceWork):
    """The device half of a plant clock (its I/O worker's thread): read the plant time
    (ms, uint32, high word first, at `address`); in lockstep, run the plant to a time and
    read it back in the same request."""

    client: ModbusClient

    def __init__(self, client: ModbusClient, address: int, out: Latest[tuple[float, float, float]]) -> None:
        super().__init__()
        self.client = client
        self.address = address
        self.out = out  # (plant time s, wall time of the last answer, wall time the plant time last moved)
        self.reads = 0
        self.failed_reads = 0  # answers that were not a plant time (exception, wrong shape)

    def counters(self) -> dict[str, Any]:
        return {"reads": self.reads, "failed_reads": self.failed_reads}

    def round(self, request: Any) -> Any:
        """None: follow the plant (read its time, publish it). ("read",): the plant time (s).
        ("run_to", t_s): run the plant to t_s, then (plant time s, state). None on no answer."""
        if request is None:
            t = self._read()
            if t is not None:
                wall = time.monotonic()
                t_s, _, changed = self.out.value
                self.out.publish((t, wall, wall) if t > t_s else (t_s, wall, changed))
            return None
        if request[0] == "read":
            return self._read()
        return self._run_to(request[1])

    def _answer(self, r: list[int] | ModbusFault) -> list[int] | None:
        if isinstance(r, LinkFault):
            raise LinkDown(r.detail)
        if isinstance(r, ModbusFault):
            self.failed_reads += 1
            self.last_error = r.detail
            return None
        self.reads += 1
        return r

    def _read(self) -> float | None:
        regs = self._answer(self.client.read_registers(self.address, 2))
        if regs is None:
            return None
        hi, lo = regs
        return ((hi << 16) | lo) / 1000.0

    def _run_to(self, t_s: float) -> tuple[float, int] | None:
        """One Modbus request (function 23, write then read): run to `t_s` — the plant steps
        before it acknowledges — and read back (plant time, state)."""
        ms = int(round(t_s * 1000.0)) & 0xFFFFFFFF
        regs = self._answer(
            self.client.read_write_registers(self.address, 3, self.address + 4, [(ms >> 16) & 0xFFFF, ms & 0xFFFF])
        )
        if regs is None:
            return None
        hi, lo, state = regs
        return ((hi << 16) | lo) / 1000.0, state


class PlantClock(Clock):
    """The plant's own clock, read over Modbus TCP (a simulator running faster than wall time).

    An I/O worker reads two holding registers (plant time in ms, uint32, high word first:
    the register map of a simulated plant's clock device) every `poll_period_s` of wall
    time; `now()` is the last plant time read, so everything on the loop clock — AR(1)'s
    Δτ, the guard's slew and staleness, the sinks' update intervals, the sources' time
    stamps — runs in plant seconds. `wait_until` sleeps until the plant reaches the
    deadline; if the plant time stops advancing for `stall_s` of wall time it returns
    anyway, so the loop can still see a stop request; if the plant has not answered for
    `lost_s` it raises RuntimeError (the run ends with the safe output: a simulation
    without its plant has nothing left to follow).
    """

    simulated = False
    kept_across_reload = True  # its connection and the plant's time go on through a reload

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
        self._time: Latest[tuple[float, float, float]] = Latest((0.0, time.monotonic(), time.monotonic()))
        self._work = PlantTimeWork(
            ModbusClient.tcp(host, port, device_id=device_id, timeout_s=timeout_s), address, self._time
        )
        # a plant that does not answer is asked again every period (no back-off: it is the clock)
        self._worker = IoWorker(
            self._work,
            name="plant-clock",
            period_s=poll_period_s,
            reconnect_min_s=poll_period_s,
            reconnect_max_s=poll_period_s,
        )

    @property
    def reads(self) -> int:
        return self._work.reads

    @property
    def errors(self) -> int:
        return self._worker.errors + self._work.failed_reads

    def start(self) -> None:
        """Start following the plant; RuntimeError if it does not answer within 5 s."""
        self._worker.start()
        if not self._worker.wait_for(lambda: self._time.count > 0, 5.0):
            self._worker.stop()
            raise RuntimeError(f"plant clock: no answer from {self.host}:{self.port}")

    def stop(self) -> None:
        self._worker.stop(2.0)

    def now(self) -> float:
        return self._time.value[0]

    def wait_until(self, deadline_s: float) -> None:
        while True:
            t_s, ok_wall, changed_wall = self._time.value
            if t_s >= deadline_s:
                return
            now = time.monotonic()
            if now - ok_wall > self.lost_s:
                raise RuntimeError(f"plant clock: no answer from {self.host}:{self.port} for {self.lost_s:g} s")
            if now - changed_wall > self.stall_s:
                return
            time.sleep(self.poll_period_s * 0.5)


class LockstepPlantClock(PlantClock):
    """A plant that waits for compd (a simulated plant's clock device in lockstep): test
    runs that give the same result however busy the machine is.

    Nothing follows the plant. `wait_until(deadline)` runs between two cycles: it waits
    until the sink's writes have been acknowledged by the device (`Sink.flush`), asks the
    clock's I/O worker to write the deadline to the plant's run-to registers and read the
    plant time back in the same request (Modbus function 23: the plant steps its physics
    and its CNC up to the deadline before it answers), then polls every polled source once,
    stamped with that time (`DrivenSource.poll_now`: their workers poll only when asked).
    So the cycle at plant time t sees the plant's signals at t, and the plant sees the
    output of every cycle before t. Every wait is for a reply, never for wall time: a
    request that fails is retried until `lost_s` (60 s) of wall time without an answer,
    and a source whose device did not answer is polled again, so a stall changes how long
    a run takes, not its result.
    """

    def __init__(self, host: str, port: int, *, device_id: int = 1, address: int = 0, lost_s: float = 60.0) -> None:
        super().__init__(host, port, device_id=device_id, address=address, timeout_s=lost_s, lost_s=lost_s)
        self._worker.reconnect_min_s = self._worker.reconnect_max_s = 0.01
        self.t_s = 0.0
        self.sink: DrivenSink | None = None
        self.sources: list[DrivenSource] = []
        self.finished = False
        self.releases = 0
        self._reads = 0
        self._errors = 0

    @property
    def reads(self) -> int:
        return self._reads

    @property
    def errors(self) -> int:
        return self._errors

    def adopt_poller(self, source: DrivenSource) -> bool:
        """A polled source this clock polls between cycles (its worker polls only when asked)."""
        if not any(source is s for s in self.sources):
            self.sources.append(source)
        return True

    def bind(self, sink: DrivenSink, sources: Sequence[object]) -> None:
        """The sink whose writes a release waits for; the sources still polled (after a reload)."""
        self.sink = sink
        self.sources = [s for s in self.sources if any(s is x for x in sources)]

    def start(self) -> None:
        self._worker.start(paced=False)
        try:
            self.t_s = self._answer(lambda: self._worker.request(("read",), self.lost_s), "no answer")
        except BaseException:
            self._worker.stop()
            raise

    def stop(self) -> None:
        self.sources = []
        self._worker.stop(2.0)

    def now(self) -> float:
        return self.t_s

    def _answer(self, request: Callable[[], Any], what: str) -> Any:
        """`request()` until it answers (not None), or RuntimeError after `lost_s` of wall time."""
        deadline = time.monotonic() + self.lost_s
        while True:
            r = request()
            if r is not None:
                self._reads += 1
                return r
            self._errors += 1
            if time.monotonic() > deadline:
                raise RuntimeError(f"plant clock (lockstep): {what} from {self.host}:{self.port} for {self.lost_s:g} s")
            time.sleep(0.01)

    def wait_until(self, deadline_s: float) -> None:
        # the sink knows what its device holds (its link read it back: the next cycle syncs), and
        # what it wrote is acknowledged: the plant never runs on while compd's output is unknown
        if self.sink is not None and not (self.sink.await_held(self.lost_s) and self.sink.flush(self.lost_s)):
            raise RuntimeError(f"lockstep: the sink's device did not answer within {self.lost_s:g} s")
        t, state = self._answer(
            lambda: self._worker.request(("run_to", deadline_s), self.lost_s), "no acknowledgement of the run-to time"
        )
        self.releases += 1
        self.t_s = max(self.t_s, t)
        self.finished = state == 2
        for s in self.sources:
            stamp = self.t_s
            self._answer(lambda s=s, stamp=stamp: True if s.poll_now(stamp) else None, f"source {s.name}: no answer")

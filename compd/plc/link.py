"""A virtual device in this process behind the Modbus link's interface: what a sink writes lands at once.

`VirtualDevice` is what the software PLC's devices share: a holding-register map
(the same map they show over Modbus) and a clock that runs their scans or IPO cycles
on simulated time. `VirtualLink` gives such a device the public interface of
`compd.io.modbus_link.ModbusLink` (start, submit, pending, flush, drain, read_now,
status, state, get_status, stop), so a sink writes to the PLC in process exactly as
it writes to one over the network. The device follows the sink's `LoopTime`: before
every access it runs whatever its clock has due by then.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

from compd.io.device_time import DeviceTime
from compd.io.histogram import DurationHist
from compd.io.mailbox import Sync


def last_due(t0_s: float, period_s: float, t_s: float) -> int:
    """The last k with t0 + k·period ≤ t (−1 when none): the last tick of an absolute
    schedule due by `t_s`, the same comparison the schedule's ticks are run with."""
    k = int(math.floor((t_s - t0_s) / period_s))
    while t0_s + (k + 1) * period_s <= t_s:
        k += 1
    while k >= 0 and t0_s + k * period_s > t_s:
        k -= 1
    return max(k, -1)


class VirtualDevice(ABC):
    """A device of the software PLC: registers, and a clock stepped on simulated time."""

    register_count: int

    @abstractmethod
    def read_registers(self, address: int, count: int) -> list[int] | None:
        """`count` registers from `address`; None if the range is not in the map."""

    @abstractmethod
    def write_registers(self, address: int, values: list[int]) -> bool:
        """Store `values` from `address`; False (nothing written) if the range is not writable."""

    @abstractmethod
    def advance_to(self, t_s: float) -> None:
        """Run every scan (IPO cycle) due up to simulated time `t_s`."""

    @abstractmethod
    def start_at(self, t_s: float) -> None:
        """Set the device's clock to `t_s`: its next scan is due then."""


class VirtualLink:
    """ModbusLink's public interface over a `VirtualDevice` in this process.

    Writes are applied when submitted (nothing is ever pending), reads are live,
    `status` is the status range read now, and `flush` brings the device's clock up to
    the sink's time. In process nothing can be lost on the way:
    the link is `up` from `start` to `stop`. A write the device refuses (an address
    outside its map, a read-only register) counts as an error, as the exception reply
    of a device over Modbus would.
    """

    def __init__(
        self,
        device: VirtualDevice,
        time: DeviceTime,
        *,
        status: tuple[int, int] | None = None,
        name: str = "sink",
        sync: list[tuple[int, int]] | None = None,
    ) -> None:
        self.device = device
        # what the device holds when the link starts (ModbusLink's sync ranges), read at `start`
        self.sync = Sync(sync) if sync is not None else None
        self.time = time
        self.status_range = status
        self.name = name
        self.state = "closed"
        self.writes = 0
        self.errors = 0
        self.bad_replies = 0
        self.last_error: str | None = None
        self.status_stamp = -1.0
        self.write_hist = DurationHist()  # kept for the interface: nothing crosses a network here
        self.latency_hist = DurationHist()

    def start(self) -> None:
        """The device's clock starts at the sink's time; what it holds is read at once."""
        self.device.start_at(self.time.now_s)
        self.state = "up"
        if self.sync is not None:
            self.sync.begin()
            regs: list[int] = []
            for address, count in self.sync.ranges:
                got = self.device.read_registers(address, count)
                if got is None:  # as over Modbus: nothing is written until it can be read
                    self.errors += 1
                    self.last_error = f"cannot read what the device holds (registers {address}+{count}): not in its map"
                    return
                regs += got
            self.sync.publish(regs)

    def held(self) -> tuple[int, list[int]] | None:
        """As ModbusLink.held: the block read at `start`, until the sink takes it."""
        return self.sync.pending() if self.sync is not None else None

    def accept(self, epoch: int) -> None:
        assert self.sync is not None
        self.sync.accept(epoch)

    def synced(self) -> bool:
        return self.sync is None or self.sync.accepted()

    def await_held(self, timeout_s: float) -> bool:
        """In process the held block is read at `start`: nothing to wait for."""
        return True

    def _run_clock(self) -> None:
        self.device.advance_to(self.time.now_s)

    def submit(self, address: int, values: list[int]) -> None:
        """Write now, after the scans due by the sink's time have run."""
        self._run_clock()
        if self.device.write_registers(address, [v & 0xFFFF for v in values]):
            self.writes += 1
        else:
            self.errors += 1
            self.last_error = f"write refused: registers {address}+{len(values)}"

    def pending(self) -> bool:
        return False

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Every write has landed already; the device's clock runs up to the sink's time."""
        self._run_clock()
        return True

    def drain(self, timeout_s: float) -> bool:
        return self.flush(timeout_s)

    def ensure_serving(self, timeout_s: float = 0.5) -> bool:
        """In process there is no worker to lose: always serving."""
        return True

    def read_now(self, address: int, count: int) -> list[int] | None:
        self._run_clock()
        return self.device.read_registers(address, count)

    @property
    def status(self) -> list[int] | None:
        """The status range as the device holds it now (None without a status range)."""
        if self.status_range is None:
            return None
        return self.read_now(*self.status_range)

    @status.setter
    def status(self, regs: list[int] | None) -> None:
        """A status read elsewhere is not kept: the device's own registers are always newer."""

    def get_status(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "writes": self.writes,
            "errors": self.errors,
            "bad_replies": self.bad_replies,
            "last_error": self.last_error,
        }

    def stop(self, timeout_s: float = 2.0) -> None:
        self.state = "closed"

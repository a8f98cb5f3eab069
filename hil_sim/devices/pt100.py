"""A PT100 transmitter's measuring side: channels, their temperatures and sensor faults.

The transport-specific devices (Modbus, DCON, CAN) wrap one `Pt100Transmitter` and
encode what `readings` returns in their own protocol. A channel reads as:
`ok` (a temperature), `burnout` (open sensor), `over`/`under` (outside the
transmitter's range). Temperatures come from the test (`set`) or from a feed
function called on every reading (a plant). The transports that run on a thread of
their own (DCON, CAN) share `ThreadedTransmitter`: the wire-fault switch and building
one from a hil_sim device section.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any, Self

from hil_sim.devices.worker import DeviceThread

SENSOR_FAULTS = ("none", "burnout", "over", "under")


class Pt100Transmitter:
    """Channels named in order, a measuring range in °C and per-channel sensor faults."""

    def __init__(
        self,
        names: Sequence[str],
        values_c: Sequence[float] | None = None,
        *,
        range_min_c: float = -50.0,
        range_max_c: float = 250.0,
    ) -> None:
        self.names = list(names)
        if not self.names:
            raise ValueError("a transmitter needs at least one channel")
        self.values_c = list(values_c) if values_c is not None else [20.0] * len(self.names)
        if len(self.values_c) != len(self.names):
            raise ValueError("one value per channel")
        self.faults = ["none"] * len(self.names)
        self.range_min_c = range_min_c
        self.range_max_c = range_max_c
        self.feed: Callable[[], Sequence[float]] | None = None
        self._lock = threading.Lock()

    def index(self, channel: int | str) -> int:
        if isinstance(channel, str):
            return self.names.index(channel)
        return channel

    def set(self, channel: int | str, value_c: float) -> None:
        with self._lock:
            self.values_c[self.index(channel)] = float(value_c)

    def set_all(self, values_c: Sequence[float]) -> None:
        with self._lock:
            self.values_c[:] = [float(v) for v in values_c]

    def set_fault(self, channel: int | str, fault: str) -> None:
        if fault not in SENSOR_FAULTS:
            raise ValueError(f"unknown sensor fault {fault!r} (known: {', '.join(SENSOR_FAULTS)})")
        with self._lock:
            self.faults[self.index(channel)] = fault

    def readings(self) -> list[tuple[str, float]]:
        """(state, °C) per channel; state is ok, burnout, over or under."""
        if self.feed is not None:
            self.set_all(self.feed())
        out = []
        with self._lock:
            for v, f in zip(self.values_c, self.faults, strict=True):
                if f != "none":
                    out.append((f, v))
                elif v != v:  # no reading (a plant's unplugged sensor): the wire is open
                    out.append(("burnout", v))
                elif v > self.range_max_c:
                    out.append(("over", v))
                elif v < self.range_min_c:
                    out.append(("under", v))
                else:
                    out.append(("ok", v))
        return out


def transmitter_from_config(cfg: dict[str, Any]) -> tuple[Pt100Transmitter, list[dict[str, Any]]]:
    """Pop `channels` and the range keys from a device section; returns the transmitter, with
    each channel's `fault` (a sensor fault) set, and the channel entries (for device-specific
    keys such as CAN ids)."""
    channels = cfg.pop("channels")
    tx = Pt100Transmitter(
        [c["name"] for c in channels],
        [float(c.get("value_c", 20.0)) for c in channels],
        range_min_c=float(cfg.pop("range_min_c", -50.0)),
        range_max_c=float(cfg.pop("range_max_c", 250.0)),
    )
    for c in channels:
        if c.get("fault"):
            tx.set_fault(c["name"], c["fault"])
    return tx, channels


class ThreadedTransmitter(DeviceThread):
    """A transmitter that serves its readings from a thread of its own (DCON module, CAN broadcaster).

    It holds the `Pt100Transmitter` it reads (`tx`) and the wire fault a test switches on
    (`fault`, one of the subclass's `wire_faults`; `slow_s` for `slow`), and builds itself
    from a hil_sim device section (`from_config`). Subclasses implement the protocol:
    `_run`, `_open`/`_close` of their line, `where`, and `_from_section`.
    """

    wire_faults: tuple[str, ...] = ("none",)

    def __init__(self, transmitter: Pt100Transmitter, slow_s: float) -> None:
        super().__init__()
        self.tx = transmitter
        self.fault = "none"
        self.slow_s = slow_s

    def set_fault(self, fault: str, slow_s: float | None = None) -> None:
        """Switch the wire fault (`none` clears it); `slow_s`, when given, is how late `slow` is."""
        if fault not in self.wire_faults:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(self.wire_faults)})")
        if slow_s is not None:
            self.slow_s = slow_s
        self.fault = fault

    @classmethod
    def _from_section(cls, tx: Pt100Transmitter, channels: list[dict[str, Any]], cfg: dict[str, Any]) -> Self:
        """The device around `tx` from what is left of its section (`channels` as written)."""
        raise NotImplementedError

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> tuple[Pt100Transmitter, Self]:
        """Transmitter and (unstarted) device from a hil_sim device section (`wire_fault` switched on)."""
        cfg = dict(cfg)
        tx, channels = transmitter_from_config(cfg)
        fault = cfg.pop("wire_fault", "none")
        dev = cls._from_section(tx, channels, cfg)
        dev.set_fault(fault)
        return tx, dev

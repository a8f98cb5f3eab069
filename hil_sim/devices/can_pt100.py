"""A PT100 transmitter that broadcasts temperatures in CAN frames (python-can; `virtual` in tests).

Every `period_s` it sends one frame per configured id; each channel is an integer
of `size` bytes at `offset` in its frame (`byte_order`, signed), counting
temperature / `scale`. A burned-out sensor sends `burnout_code`, out of range
`over_code` / `under_code` (raw unsigned codes). Wire faults: no_answer (silence),
garbage (frames too short to hold their channels), crc_error (an error frame in
place of each data frame, as a controller that saw a bad CRC does), slow (frames
every `slow_s` instead of `period_s`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import can

from hil_sim.devices.pt100 import Pt100Transmitter, ThreadedTransmitter

WIRE_FAULTS = ("none", "no_answer", "garbage", "crc_error", "slow")


@dataclass
class CanChannel:
    """Where one channel sits: frame `can_id`, `size` bytes at `offset`, counting °C / `scale`."""

    name: str
    can_id: int
    offset: int = 0
    size: int = 2
    signed: bool = True
    byte_order: str = "little"
    scale: float = 0.1


class CanPt100(ThreadedTransmitter):
    """Broadcasts a transmitter's readings on a CAN bus from its own thread."""

    wire_faults = WIRE_FAULTS
    thread_name = "can-pt100"

    def __init__(
        self,
        transmitter: Pt100Transmitter,
        channels: list[CanChannel],
        *,
        interface: str = "virtual",
        channel: str = "vcan0",
        period_s: float = 0.1,
        burnout_code: int = 0x8000,
        over_code: int = 0x7FFF,
        under_code: int = 0x8001,
        extended_id: bool = False,
    ) -> None:
        super().__init__(transmitter, slow_s=1.0)
        self.channels = channels
        self.interface, self.channel = interface, channel
        self.period_s = period_s
        self.codes = {"burnout": burnout_code, "over": over_code, "under": under_code}
        self.extended_id = extended_id
        self.frames_sent = 0
        self._bus: can.BusABC | None = None

    def frames(self) -> list[can.Message]:
        """This period's data frames."""
        data: dict[int, bytearray] = {}
        for ch, (state, v) in zip(self.channels, self.tx.readings(), strict=True):
            buf = data.setdefault(ch.can_id, bytearray(8))
            if state == "ok":
                raw = int(round(v / ch.scale))
                b = raw.to_bytes(ch.size, ch.byte_order, signed=ch.signed)
            else:
                b = (self.codes[state] & ((1 << (8 * ch.size)) - 1)).to_bytes(ch.size, ch.byte_order)
            buf[ch.offset : ch.offset + ch.size] = b
        out = []
        for can_id, buf in data.items():
            n = max(c.offset + c.size for c in self.channels if c.can_id == can_id)
            out.append(can.Message(arbitration_id=can_id, data=bytes(buf[:n]), is_extended_id=self.extended_id))
        return out

    def _run(self) -> None:
        assert self._bus is not None
        while not self._stop.is_set():
            f = self.fault
            for msg in self.frames():
                if f == "no_answer":
                    break
                if f == "garbage":
                    msg = can.Message(
                        arbitration_id=msg.arbitration_id, data=msg.data[:1], is_extended_id=self.extended_id
                    )
                elif f == "crc_error":
                    msg = can.Message(is_error_frame=True)
                self._bus.send(msg)
                self.frames_sent += 1
            self._stop.wait(self.slow_s if f == "slow" else self.period_s)

    def _open(self) -> None:
        self._bus = can.Bus(interface=self.interface, channel=self.channel)

    def _close(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def where(self) -> str:
        return f"can:{self.interface}:{self.channel} ids {sorted({c.can_id for c in self.channels})}"

    @classmethod
    def _from_section(cls, tx: Pt100Transmitter, channels: list[dict[str, Any]], cfg: dict[str, Any]) -> CanPt100:
        layout = [CanChannel(**{k: v for k, v in c.items() if k not in ("value_c", "fault")}) for c in channels]
        return cls(tx, layout, **cfg)

"""Shape checks for Modbus register reads: a reply is data only if it answers the request asked.

pymodbus 3.16's sync client matches a reply to its request by transaction id and unit id
(a mismatch is skipped, and the request times out), and rejects a byte count longer than
the frame; but it hands back whatever function code and register count the peer sent:
a 0x04 reply to a 0x03 request, six registers for four asked, or a byte count shorter
than the frame all arrive as a normal response. The Modbus source, the sinks' link and
the plant clock check every reply here before they use a register of it.
"""

from __future__ import annotations

from typing import Any

HOLDING = 0x03
INPUT = 0x04


def shape_error(rr: Any, function_code: int, count: int, device_id: int | None = None) -> str | None:
    """Why `rr` is not a reply to a read of `count` registers with `function_code` from
    `device_id` (None: it is). Call it on non-exception replies."""
    dev = getattr(rr, "dev_id", None)
    if device_id is not None and isinstance(dev, int) and dev != device_id:
        return f"reply from unit {dev}, asked unit {device_id}"
    fc = getattr(rr, "function_code", None)
    if fc != function_code:
        return f"reply function 0x{fc:02X}, asked 0x{function_code:02X}" if isinstance(fc, int) else "no function code"
    regs = getattr(rr, "registers", None)
    if regs is None or len(regs) != count:
        return f"reply has {0 if regs is None else len(regs)} registers, asked {count}"
    return None


class FrameTap:
    """pymodbus's `trace_packet` hook: keeps the bytes last received, so the reply's MBAP
    length and byte count can be checked (pymodbus reads as many registers as the byte
    count says and ignores the rest of the frame). Modbus TCP only."""

    def __init__(self) -> None:
        self.last = b""

    def __call__(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self.last = data
        return data

    def tcp_error(self, transaction_id: int, count: int) -> str | None:
        """Why the received frame with `transaction_id` does not carry exactly `count`
        registers (None: it does, or it is not in the buffer)."""
        buf = self.last
        while len(buf) >= 9:
            length = int.from_bytes(buf[4:6], "big")
            if int.from_bytes(buf[0:2], "big") == transaction_id:
                if buf[7] & 0x80:
                    return None  # an exception reply: the caller has it already
                if length != 3 + 2 * count or buf[8] != 2 * count:
                    return f"frame length {length}, byte count {buf[8]} for {count} registers"
                return None
            buf = buf[6 + length :]
        return None

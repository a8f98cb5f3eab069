"""A PT100 Modbus module (TCP or RTU): temperatures as scaled registers, fault codes, status words.

Register map (holding and input registers alike), for channel i:
* value at `value_address + i·width` (width 1 for 16-bit types, 2 for 32-bit), the
  temperature divided by `scale`, in `data_type`, `byte_order` and `word_order`;
  a burned-out sensor reads `burnout_code`, over range `over_code`, under range `under_code`
  (raw register contents, e.g. 0x8000 / 0x7FFF / 0x8001 for int16);
* status at `status_address + i` (if given): 0 ok, bit 0 burn-out, bit 1 over, bit 2 under.
"""

from __future__ import annotations

import math
import struct
from typing import Any

from hil_sim.devices.modbus_server import ModbusServerThread, WireFaults
from hil_sim.devices.pt100 import Pt100Transmitter, transmitter_from_config

FORMATS = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}
STATUS_BITS = {"ok": 0, "burnout": 1, "over": 2, "under": 4}


def encode_value(value: float, data_type: str, byte_order: str, word_order: str) -> list[int]:
    """A number as 1 or 2 registers (integers are rounded, floats kept)."""
    fmt = FORMATS[data_type]
    v: Any = value if fmt == "f" else int(round(value))
    raw = struct.pack(">" + fmt, v)
    words = [raw[i : i + 2] for i in range(0, len(raw), 2)]
    if byte_order == "little":
        words = [w[::-1] for w in words]
    if word_order == "little":
        words = words[::-1]
    return [int.from_bytes(w, "big") for w in words]


def code_registers(code: int, width: int, word_order: str) -> list[int]:
    """A raw code (as the registers read, high word first) in register order."""
    words = [(code >> 16) & 0xFFFF, code & 0xFFFF] if width == 2 else [code & 0xFFFF]
    return words[::-1] if word_order == "little" else words


class Pt100ModbusDevice:
    """The register map of a PT100 module around a `Pt100Transmitter`."""

    def __init__(
        self,
        transmitter: Pt100Transmitter,
        *,
        value_address: int = 0,
        status_address: int | None = None,
        data_type: str = "int16",
        scale: float = 0.1,
        byte_order: str = "big",
        word_order: str = "big",
        burnout_code: int = 0x8000,
        over_code: int = 0x7FFF,
        under_code: int = 0x8001,
        register_count: int = 64,
    ) -> None:
        if data_type not in FORMATS:
            raise ValueError(f"data_type must be one of {', '.join(FORMATS)}")
        self.tx = transmitter
        self.value_address = value_address
        self.status_address = status_address
        self.data_type = data_type
        self.width = 2 if data_type.endswith("32") else 1
        self.scale = scale
        self.byte_order = byte_order
        self.word_order = word_order
        self.codes = {"burnout": burnout_code, "over": over_code, "under": under_code}
        self.register_count = register_count
        n = len(transmitter.names)
        end = value_address + n * self.width
        if status_address is not None:
            end = max(end, status_address + n)
        if end > register_count:
            raise ValueError(f"register map needs {end} registers, register_count is {register_count}")

    def snapshot(self) -> list[int]:
        regs = [0] * self.register_count
        for i, (state, v) in enumerate(self.tx.readings()):
            a = self.value_address + i * self.width
            if state == "ok":
                words = encode_value(v / self.scale, self.data_type, self.byte_order, self.word_order)
            elif self.data_type == "float32" and state == "burnout":
                words = encode_value(math.nan, "float32", self.byte_order, self.word_order)
            else:
                words = code_registers(self.codes[state], self.width, self.word_order)
            regs[a : a + self.width] = words
            if self.status_address is not None:
                regs[self.status_address + i] = STATUS_BITS[state]
        return regs

    def read_registers(self, address: int, count: int) -> list[int] | None:
        if address < 0 or address + count > self.register_count:
            return None
        return self.snapshot()[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> bool:
        return False  # a transmitter's map is read-only


def from_config(cfg: dict[str, Any]) -> tuple[Pt100Transmitter, Pt100ModbusDevice, ModbusServerThread]:
    """Build transmitter, register map and (unstarted) server from a hil_sim device section."""
    cfg = dict(cfg)
    tx, _ = transmitter_from_config(cfg)
    transport = cfg.pop("transport", "tcp")
    server_kw: dict[str, Any] = {"device_id": int(cfg.pop("device_id", 1))}
    if transport == "tcp":
        server_kw["host"] = cfg.pop("host", "127.0.0.1")
        server_kw["port"] = int(cfg.pop("port", 0))
    elif transport == "rtu":
        server_kw["serial_port"] = cfg.pop("serial_port")
        server_kw["baudrate"] = int(cfg.pop("baudrate", 115200))
        server_kw["parity"] = cfg.pop("parity", "N")
    else:
        raise ValueError(f"transport must be tcp or rtu, got {transport!r}")
    fault = cfg.pop("wire_fault", "none")
    dev = Pt100ModbusDevice(tx, **cfg)
    faults = WireFaults()
    faults.set(fault)
    return tx, dev, ModbusServerThread(dev, faults=faults, **server_kw)

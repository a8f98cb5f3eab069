"""A pymodbus server (TCP or RTU) on its own asyncio thread, backed by a device's register map.

The device owns its registers (`read_registers`/`write_registers`); the server calls
them through a pymodbus `SimDevice` action on every request, so the device's state is
the only truth and a scan thread may change it between requests. Faults that live on
the wire (no answer, garbage bytes, CRC error, slow answer, exception reply) are
applied here, so every device served over Modbus can show them.
"""

from __future__ import annotations

import asyncio
import os
import threading
from dataclasses import dataclass
from typing import Any, Protocol

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

FAULTS = ("none", "no_answer", "garbage", "crc_error", "slow", "exception")


class RegisterDevice(Protocol):
    """What a device served over Modbus provides: a holding-register map."""

    register_count: int

    def read_registers(self, address: int, count: int) -> list[int] | None: ...
    def write_registers(self, address: int, values: list[int]) -> bool: ...


@dataclass
class WireFaults:
    """Faults a test switches on; read by the server on every reply."""

    mode: str = "none"
    slow_s: float = 0.5
    exception_code: int = int(ExcCodes.DEVICE_FAILURE)

    def set(self, mode: str, **kw: Any) -> None:
        if mode not in FAULTS:
            raise ValueError(f"unknown fault {mode!r} (known: {', '.join(FAULTS)})")
        for k, v in kw.items():
            setattr(self, k, v)
        self.mode = mode


class ModbusServerThread:
    """Serves `device` over Modbus TCP (`host`, `port`; port 0 picks one) or RTU (`serial_port`).

    Holding registers (FC 3/6/16) and input registers (FC 4) both map to the device's
    one register map, addresses 0 .. register_count−1, `device_id` as the unit id.
    """

    def __init__(
        self,
        device: RegisterDevice,
        *,
        device_id: int = 1,
        host: str = "127.0.0.1",
        port: int | None = None,
        serial_port: str | None = None,
        baudrate: int = 115200,
        parity: str = "N",
        faults: WireFaults | None = None,
    ) -> None:
        if (port is None) == (serial_port is None):
            raise ValueError("give either a TCP port or a serial port")
        self.device = device
        self.device_id = device_id
        self.host = host
        self.port = port
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.parity = parity
        self.faults = faults or WireFaults()
        self.requests = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # ---------------------------------------------------------------- server side
    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        self.requests += 1
        f = self.faults
        if f.mode == "slow":
            await asyncio.sleep(f.slow_s)
        elif f.mode == "exception":
            return ExcCodes(f.exception_code)
        if set_values is not None:
            if not self.device.write_registers(address, [int(v) for v in set_values]):
                return ExcCodes.ILLEGAL_ADDRESS
            return None
        values = self.device.read_registers(address, count)
        if values is None:
            return ExcCodes.ILLEGAL_ADDRESS
        off = address - start_address
        registers[off : off + count] = [v & 0xFFFF for v in values]
        return None

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        mode = self.faults.mode
        if mode == "no_answer":
            return b""
        if mode == "garbage":
            return os.urandom(3) + b"\xff\x00" + os.urandom(max(len(data) - 5, 2))
        if mode == "crc_error" and len(data) > 6:
            if self.serial_port is not None:  # RTU: the CRC (last two bytes) goes wrong
                return data[:-1] + bytes([data[-1] ^ 0x5A])
            # TCP carries no CRC (the stack checks it): corrupt the MBAP length instead
            return data[:5] + bytes([data[5] ^ 0x40]) + data[6:]
        return data

    async def _serve(self) -> None:
        sim = SimDevice(
            id=self.device_id,
            simdata=[SimData(0, count=self.device.register_count, datatype=DataType.REGISTERS)],
            action=self._action,
        )
        if self.serial_port is not None:
            self._server = ModbusSerialServer(
                sim,
                framer=FramerType.RTU,
                port=self.serial_port,
                baudrate=self.baudrate,
                parity=self.parity,
                trace_packet=self._trace_packet,
            )
        else:
            self._server = ModbusTcpServer(sim, address=(self.host, self.port or 0), trace_packet=self._trace_packet)
        await self._server.serve_forever(background=True)
        if self.serial_port is None:
            sock = self._server.transport.sockets[0]
            self.port = sock.getsockname()[1]

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve())
        except BaseException as e:  # reported to start()
            self._error = e
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            try:
                loop.run_until_complete(self._server.shutdown())
                pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for t in pending:
                    t.cancel()
                if pending:
                    loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            finally:
                loop.close()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> ModbusServerThread:
        name = f"modbus-{'rtu' if self.serial_port else 'tcp'}-server"
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        if not self._ready.wait(10):
            raise RuntimeError("Modbus server did not start")
        if self._error is not None:
            self._thread.join(5)
            raise RuntimeError(f"Modbus server failed to start: {self._error}")
        return self

    def stop(self) -> None:
        if self._thread is None:
            return
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._thread = None

    def where(self) -> str:
        if self.serial_port is not None:
            return f"rtu:{self.serial_port}@{self.baudrate} id {self.device_id}"
        return f"tcp:{self.host}:{self.port} id {self.device_id}"

    def __enter__(self) -> ModbusServerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

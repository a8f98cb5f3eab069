"""A modbus source reading coils or discrete inputs from a pymodbus server on 127.0.0.1.

The bits are a PLC's inhibit and referenced signals.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest
from pydantic import ValidationError
from pymodbus.client import ModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from compd.sources.modbus import ModbusConfig, ModbusSource
from tests.sources.helpers import Harness


class BitServer:
    """A pymodbus TCP server with 16 coils, 16 discrete inputs and 16 of each register table."""

    def __init__(self) -> None:
        self.port = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Any = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bit-server", daemon=True)

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop

        async def serve() -> None:
            bits = [SimData(0, count=16, datatype=DataType.BITS)]
            regs = [SimData(0, count=16, datatype=DataType.REGISTERS)]
            sim = SimDevice(
                id=1,
                simdata=(
                    bits,
                    [SimData(0, count=16, datatype=DataType.BITS)],
                    regs,
                    [SimData(0, count=16, datatype=DataType.REGISTERS)],
                ),
            )
            self._server = ModbusTcpServer(sim, address=("127.0.0.1", 0))
            await self._server.serve_forever(background=True)
            self.port = self._server.transport.sockets[0].getsockname()[1]

        try:
            loop.run_until_complete(serve())
            self._ready.set()
            loop.run_forever()
        finally:
            loop.run_until_complete(self._server.shutdown())
            pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for t in pending:
                t.cancel()
            if pending:
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.close()

    def __enter__(self) -> BitServer:
        self._thread.start()
        assert self._ready.wait(10), "the pymodbus server did not start"
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)

    def set_coil(self, address: int, on: bool) -> None:
        """What the CNC's PLC does: write a coil (function 5) over its own connection."""
        c = ModbusTcpClient("127.0.0.1", port=self.port)
        try:
            assert c.connect()
            assert not c.write_coil(address, on, device_id=1).isError()
        finally:
            c.close()


def _cfg(port: int, **kw: Any) -> ModbusConfig:
    base = {
        "kind": "modbus",
        "name": "plc",
        "port": port,
        "poll_period_s": 0.01,
        "timeout_s": 0.2,
        "reconnect_min_s": 0.02,
        "reconnect_max_s": 0.1,
        "function": "coils",
        "channels": [{"name": "cnc_inhibit", "address": 2}, {"name": "z_referenced", "address": 5}],
    }
    base.update(kw)
    return ModbusConfig.model_validate(base)


def test_coils_read_as_signal_bits():
    with BitServer() as srv, Harness(ModbusSource(_cfg(srv.port))) as h:
        assert h.source.requests == [(2, 1), (5, 1)]
        assert h.sample() == {"cnc_inhibit": (0.0, "GOOD"), "z_referenced": (0.0, "GOOD")}
        srv.set_coil(2, True)
        srv.set_coil(5, True)
        assert h.sample(polls=2) == {"cnc_inhibit": (1.0, "GOOD"), "z_referenced": (1.0, "GOOD")}


def test_discrete_inputs_read_too():
    with BitServer() as srv, Harness(ModbusSource(_cfg(srv.port, function="discrete"))) as h:
        assert h.sample() == {"cnc_inhibit": (0.0, "GOOD"), "z_referenced": (0.0, "GOOD")}


def test_a_bit_table_channel_is_one_bit():
    with pytest.raises(ValidationError, match="a channel is one bit"):
        _cfg(1, channels=[{"name": "x", "address": 0, "bit": 3}])
    with pytest.raises(ValidationError, match="a channel is one bit"):
        _cfg(1, data_type="float32")

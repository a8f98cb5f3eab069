"""Probe results from the CNC: its probe-result block polled over Modbus TCP, each new result to the adapter.

The CNC's probing cycle writes each result into an 8-register block (compd.plc.probe_block:
sequence, axis index, deviation nm, position µm, σ nm, sequence again) — the FANUC PMC's
D100–D107 at registers 500–507, the Siemens NC's at 1000–1007 (`cnc`), or `address`.
The source's I/O worker reads the block every `poll_period_s` (in lockstep, once per
cycle at the plant time); when the sequence number has changed since the last poll,
it hands the adapter one `Probe` stamped with the poll's loop time: the deviation
measured with compd's correction in place (`residual`), so the adapter adds back the
correction applied then. The source publishes no signal into the frame.

A result already in the block at the first poll, or after a lost connection, is of
unknown age: it only sets the sequence number to compare with, and is not used. A
block whose two sequence numbers differ is being written: the next poll reads it. A
reply of the wrong shape (`compd.io.modbus_client`), an exception reply or an axis
index outside `axes` is a comms fault counted in the status, never a probe.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Any, Literal

from pydantic import Field, model_validator

from compd.core.config import SourceConfig
from compd.core.frame import Frame
from compd.core.probe import Probe
from compd.io.modbus_client import (
    BadReply,
    ExceptionReply,
    LinkFault,
    ModbusClient,
    NoConnection,
    OverModbus,
)
from compd.io.ring import MessageRing
from compd.io.worker import DeviceWork, LinkDown, stall_after
from compd.plc.probe_block import PROBE_COUNT, decode_result
from compd.sources.base import PolledSource

log = logging.getLogger("compd.sources.probe")

BLOCK_ADDRESS = {"fanuc_pmc": 500, "siemens_nc": 1000}
PROBE_RING_BYTES = 64 << 10  # probes waiting for the cycle (a few hundred)


class ProbeConfig(SourceConfig):
    """The CNC's probe-result block on Modbus TCP (the PMC's or the NC's gateway)."""

    host: str = Field("127.0.0.1", description="the CNC's Modbus TCP gateway (the one its sink writes to)")
    port: int = Field(502, ge=1, le=65535, description="its TCP port")
    device_id: int = Field(1, ge=0, le=247, description="unit id")
    cnc: Literal["fanuc_pmc", "siemens_nc"] = Field(
        description="whose register map: fanuc_pmc (block at 500, PMC D100–D107) or siemens_nc (block at 1000)"
    )
    address: int | None = Field(
        None, ge=0, le=65535 - PROBE_COUNT, description="first register of the block, if not the cnc's default"
    )
    axes: list[str] = Field(min_length=1, description="axis names in the block's axis-index order (0, 1, …)")
    function: Literal["holding", "input"] = Field("holding", description="register table")
    poll_period_s: float = Field(
        0.5, ge=0.001, le=60, description="read the block this often; faster than the CNC probes"
    )
    timeout_s: float = Field(0.25, ge=0.001, le=30, description="wait this long for a reply")
    reconnect_min_s: float = Field(0.1, ge=0.01, le=60)
    reconnect_max_s: float = Field(10.0, ge=0.01, le=3600, description="at least reconnect_min_s")

    @model_validator(mode="after")
    def _check(self) -> ProbeConfig:
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s is below reconnect_min_s")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError("an axis name is used twice")
        return self


class ProbeSource(PolledSource):
    """The CNC's probe-result block, polled by an I/O worker; no frame signals."""

    Config = ProbeConfig

    def __init__(self, cfg: ProbeConfig, base_dir: str = ".") -> None:
        self.stall_after_s = stall_after(cfg.timeout_s)
        super().__init__(cfg, base_dir)
        self.cfg: ProbeConfig = cfg
        self.poll_period_s = cfg.poll_period_s
        self.reconnect_min_s, self.reconnect_max_s = cfg.reconnect_min_s, cfg.reconnect_max_s
        self.address = cfg.address if cfg.address is not None else BLOCK_ADDRESS[cfg.cnc]
        self._out = MessageRing(PROBE_RING_BYTES)  # made before a fork: the poller's process puts, the cycle takes
        self._used = False
        self._poller: ProbePoller | None = None

    def signal_names(self) -> list[str]:
        return []

    def bind_probes(self, inbox: deque[Probe]) -> None:
        self._used = True

    def probe_ring(self) -> MessageRing:
        return self._out

    def open(self, now_s: float) -> None:
        if not self._used:
            log.warning(
                "%s: no adapt section: probe results are read but not used",
                self.name,
                extra={"event": "probe_unused", "source": self.name},
            )

    def make_poller(self, snapshot: Any) -> ProbePoller:  # type: ignore[override]  # no snapshot: no signals
        self._poller = ProbePoller(self.cfg, self.address, self._out, self.name)
        return self._poller

    @property
    def polls(self) -> int:
        """Well-formed blocks read."""
        return self._poller.polls if self._poller is not None else 0

    def sampled(self) -> bool:
        """No signals: nothing for the cycle to wait for."""
        return True

    def read(self, frame: Frame, now_s: float) -> None:
        """Nothing to copy: probes reach the adapter through `probe_ring`."""

    def get_status(self) -> dict[str, Any]:
        io = self.io_status()
        return {
            **super().get_status(),
            "cnc": self.cfg.cnc,
            "address": self.address,
            **{
                k: io.get(k)
                for k in (
                    "state",
                    "polls",
                    "probes",
                    "missed",
                    "torn",
                    "bad_axis",
                    "exception_replies",
                    "comm_errors",
                    "malformed_replies",
                    "last_seq",
                    "last_error",
                )
            },
        }


class ProbePoller(OverModbus, DeviceWork):
    """The device half, on the worker's thread: read the block, compare its sequence number,
    hand a new result on."""

    client: ModbusClient

    def __init__(self, cfg: ProbeConfig, address: int, out: MessageRing, name: str) -> None:
        super().__init__()
        self.cfg = cfg
        self.address = address
        self.out = out
        self.name = name
        self.client = ModbusClient.tcp(cfg.host, cfg.port, device_id=cfg.device_id, timeout_s=cfg.timeout_s)
        self.last_seq: int | None = None  # None: take the next result read as the baseline
        self.polls = self.probes = self.missed = self.torn = self.bad_axis = 0
        self.exception_replies = self.comm_errors = self.malformed_replies = 0

    def counters(self) -> dict[str, Any]:
        return {
            "polls": self.polls,
            "probes": self.probes,
            "missed": self.missed,
            "torn": self.torn,
            "bad_axis": self.bad_axis,
            "exception_replies": self.exception_replies,
            "comm_errors": self.comm_errors,
            "malformed_replies": self.malformed_replies,
            "last_seq": self.last_seq,
        }

    def connect(self) -> None:
        self.last_seq = None  # results that came while the link was down are of unknown age
        OverModbus.connect(self)

    def round(self, request: Any) -> bool:
        """One read of the block stamped `request` (a lockstep clock's time) or now; True when
        the device answered with a well-formed block."""
        stamp = self.now() if request is None else float(request)
        r = self.client.read_registers(self.address, PROBE_COUNT, table=self.cfg.function)
        if isinstance(r, NoConnection):
            self.last_error = r.detail
            raise LinkDown(r.detail)
        if isinstance(r, LinkFault):
            self.comm_errors += 1
            self.last_error = r.detail
            raise LinkDown(r.detail)
        if isinstance(r, ExceptionReply):
            self.exception_replies += 1
            self.last_error = r.detail
            return False
        if isinstance(r, BadReply) or not isinstance(r, list) or len(r) != PROBE_COUNT:
            self.malformed_replies += 1
            self.last_error = r.detail if isinstance(r, BadReply) else f"probe block: {r!r:.80}"
            return False
        self.polls += 1
        res = decode_result(r)
        if res is None:  # the CNC is writing a result: read it whole next time
            self.torn += 1
            return True
        if self.last_seq is None or res.seq == self.last_seq:
            self.last_seq = res.seq
            return True
        self.missed += (res.seq - self.last_seq - 1) & 0xFFFF
        self.last_seq = res.seq
        if res.axis >= len(self.cfg.axes):
            self.bad_axis += 1
            self.last_error = f"probe result {res.seq}: axis index {res.axis}, but axes has {len(self.cfg.axes)}"
            log.warning("%s: %s", self.name, self.last_error, extra={"event": "probe_bad_axis", "source": self.name})
            return True
        probe = Probe(
            t_s=stamp,
            axis=self.cfg.axes[res.axis],
            error_um=res.deviation_um,
            sigma_um=res.sigma_um,
            position_mm=res.position_mm,
            source=self.name,
            residual=True,
        )
        self.probes += 1
        if not self.out.put(probe):
            self.last_error = f"probe result {res.seq}: dropped, the cycle is not taking probes"
        return True

    def offline(self, request: Any) -> bool:
        return False

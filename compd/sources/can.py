"""Temperatures carried in CAN frames (python-can): socketcan in production, `virtual` in tests.

Each signal is an integer of `size` bytes at `offset` in the frame with id `id`,
value_c = raw · scale + offset_c. A reader on an I/O worker decodes frames as they come
and stamps each signal with the loop clock; `read` copies the newest values. Raw codes
mean burn-out or out of range. A frame's data is its first DLC bytes (never padding
beyond the DLC); a frame whose DLC does not cover offset + size of every signal
configured on its id is not the layout configured: all of that id's signals go
COMMS_LOST at once and `bad_frames` counts it. Remote (RTR) frames carry no data
and are ignored. No frame for `timeout_s` (silence, or only error frames, which is
what a bad CRC produces on a real bus) makes them COMMS_LOST; a sample older than
`stale_after_s` reads STALE.
"""

from __future__ import annotations

from collections.abc import Container
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from compd.core.clock import Clock
from compd.core.config import SourceConfig, Strict
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.io.child import hosting_now
from compd.io.mailbox import Snapshot
from compd.io.worker import DeviceWork, IoWorker
from compd.sources.base import Source


class CanSignal(Strict):
    """Where one temperature sits in a frame."""

    name: str = Field(min_length=1)
    id: int = Field(ge=0, le=0x1FFFFFFF, description="arbitration id")
    offset: int = Field(0, ge=0, le=7, description="first byte")
    size: Literal[1, 2, 4] = 2
    signed: bool = True
    byte_order: Literal["little", "big"] = "little"
    scale: float = Field(0.1, ge=-1e6, le=1e6, description="°C per count; not 0")
    offset_c: float = Field(0.0, ge=-1000, le=1000, description="added after scaling")

    @model_validator(mode="after")
    def _fits(self) -> CanSignal:
        if self.offset + self.size > 8:
            raise ValueError("offset + size exceeds the 8 data bytes of a CAN frame")
        if self.scale == 0:
            raise ValueError("scale 0 would read every temperature as offset_c")
        return self


class CanConfig(SourceConfig):
    """A CAN bus and the temperatures it carries."""

    interface: str = Field("socketcan", description="python-can interface (virtual in tests)")
    channel: str = Field("can0")
    bitrate: int | None = Field(None, ge=1000, le=1_000_000, description="bit/s (CAN: at most 1 Mbit/s)")
    burnout_codes: list[Annotated[int, Field(ge=0, le=0xFFFFFFFF)]] = Field(
        default_factory=lambda: [0x8000], description="raw unsigned codes"
    )
    out_of_range_codes: list[Annotated[int, Field(ge=0, le=0xFFFFFFFF)]] = Field(
        default_factory=lambda: [0x7FFF, 0x8001]
    )
    timeout_s: float = Field(1.0, ge=0.001, le=3600, description="no frame this long: COMMS_LOST")
    stale_after_s: float | None = Field(None, ge=0.001, le=86400)
    signals: list[CanSignal] = Field(min_length=1)

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, name: str) -> str:
        from can.interfaces import VALID_INTERFACES

        if name not in VALID_INTERFACES:
            raise ValueError(f"python-can has no interface {name!r} (known: {', '.join(sorted(VALID_INTERFACES))})")
        return name

    @model_validator(mode="after")
    def _unique(self) -> CanConfig:
        names = [s.name for s in self.signals]
        if len(set(names)) != len(names):
            raise ValueError("a signal name is used twice")
        return self


def decode_signal(
    data: bytes, sig: CanSignal, burnout: Container[int], out_of_range: Container[int]
) -> tuple[float, int]:
    """(value °C, quality) of one signal in a frame's data; raw unsigned codes in `burnout`
    or `out_of_range` are those qualities."""
    if len(data) < sig.offset + sig.size:
        return np.nan, Quality.COMMS_LOST
    b = bytes(data[sig.offset : sig.offset + sig.size])
    raw = int.from_bytes(b, sig.byte_order, signed=False)
    if raw in burnout:
        return np.nan, Quality.BURNOUT
    if raw in out_of_range:
        return np.nan, Quality.OUT_OF_RANGE
    v = int.from_bytes(b, sig.byte_order, signed=sig.signed)
    return v * sig.scale + sig.offset_c, Quality.GOOD


class CanSource(Source):
    """Temperatures decoded by a CAN reader on an I/O worker; `read` never blocks."""

    Config = CanConfig

    def __init__(self, cfg: CanConfig, base_dir: str = ".") -> None:
        super().__init__(cfg, base_dir)
        self.cfg: CanConfig = cfg
        self._snapshot = Snapshot(len(cfg.signals))
        self._worker: IoWorker | None = None

    def signal_names(self) -> list[str]:
        return [s.name for s in self.cfg.signals]

    def decode(self, data: bytes, sig: CanSignal) -> tuple[float, int]:
        """(value °C, quality) of one signal in a frame's data."""
        return decode_signal(data, sig, self.cfg.burnout_codes, self.cfg.out_of_range_codes)

    @property
    def worker(self) -> IoWorker:
        """The I/O worker that reads the bus (built on first use)."""
        if self._worker is None:
            reader = CanReader(self.cfg, self._snapshot, self.config_path)
            self._worker = IoWorker(
                reader, name=f"can-{self.name}", period_s=0.0, reconnect_min_s=0.1, reconnect_max_s=5.0
            )
        return self._worker

    def start_polling(self, clock: Clock) -> None:
        """Open the bus on the reader's thread (an interface python-can does not know or a
        channel that does not exist is bad input naming the key, raised here: start-up
        fails loudly) and decode frames as they come, stamped with the loop clock."""
        worker = self.worker
        assert isinstance(worker.work, CanReader)
        worker.work.config_path = self.config_path  # set by the app after construction
        host = hosting_now()
        # python-can's virtual bus lives in this process: its reader stays here
        process = host.process and self.cfg.interface != "virtual"
        worker.start(clock=clock.now, process=process, avoid_cpus=host.cpus)

    def read(self, frame: Frame, now_s: float) -> None:
        idx = self._idx
        self._snapshot.copy_to(frame, idx)
        age = now_s - frame.stamp_s[idx]
        q = frame.quality[idx]
        q = np.where((age > self.cfg.timeout_s) & (q != Quality.NO_DATA), Quality.COMMS_LOST, q)
        if self.cfg.stale_after_s is not None:
            q = np.where((q == Quality.GOOD) & (age > self.cfg.stale_after_s), Quality.STALE, q)
        frame.quality[idx] = q

    def close(self) -> None:
        if self._worker is not None:
            self._worker.stop()

    def get_status(self) -> dict[str, Any]:
        io = self.worker.get_status()
        return {
            **super().get_status(),
            "frames": io["frames"],
            "error_frames": io["error_frames"],
            "bad_frames": io["bad_frames"],
            "last_error": io["last_error"],
        }


class CanReader(DeviceWork):
    """The device half of a CAN source: the bus, one frame per round (the worker's thread)."""

    def __init__(self, cfg: CanConfig, snapshot: Snapshot, config_path: tuple[str | int, ...] = ()) -> None:
        super().__init__()
        self.cfg = cfg
        self.snapshot = snapshot
        self.config_path = config_path
        n = len(cfg.signals)
        self._by_id: dict[int, list[tuple[int, CanSignal]]] = {}
        for i, s in enumerate(cfg.signals):
            self._by_id.setdefault(s.id, []).append((i, s))
        self._need = {fid: max(s.offset + s.size for _, s in sigs) for fid, sigs in self._by_id.items()}
        self._burnout = frozenset(cfg.burnout_codes)
        self._out_of_range = frozenset(cfg.out_of_range_codes)
        self._values = np.full(n, np.nan)
        self._quality = np.full(n, Quality.NO_DATA, dtype=np.uint8)
        self._stamp = np.full(n, -np.inf)
        self._bus: Any = None
        self.frames = 0
        self.error_frames = 0
        self.bad_frames = 0

    def open(self) -> None:
        """Open the bus; an interface python-can does not know or a channel that does not
        exist is bad input naming the key (`interface`, `channel`)."""
        import errno

        import can

        kw: dict[str, Any] = {"interface": self.cfg.interface, "channel": self.cfg.channel}
        if self.cfg.bitrate:
            kw["bitrate"] = self.cfg.bitrate
        try:
            self._bus = can.Bus(**kw)
        except can.CanInterfaceNotImplementedError as e:
            known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            raise BadInput(
                f"cannot open CAN interface {self.cfg.interface!r}: {e} (known: {known})",
                path=(*self.config_path, "interface"),
            ) from None
        except OSError as e:
            if e.errno in (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT):  # no SocketCAN in this kernel
                raise BadInput(
                    f"cannot open CAN interface {self.cfg.interface!r}: {e.strerror or e}",
                    path=(*self.config_path, "interface"),
                ) from None
            raise BadInput(
                f"cannot open CAN channel {self.cfg.channel!r}: {e.strerror or e}", path=(*self.config_path, "channel")
            ) from None
        except ImportError as e:  # the interface's driver library is not installed
            raise BadInput(
                f"cannot open CAN interface {self.cfg.interface!r}: {e}", path=(*self.config_path, "interface")
            ) from None
        except (can.CanError, ValueError) as e:  # slcan/serial: no such device; a bad bitrate
            raise BadInput(
                f"cannot open CAN channel {self.cfg.channel!r} ({self.cfg.interface}): {e}",
                path=(*self.config_path, "channel"),
            ) from None

    def close(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def counters(self) -> dict[str, Any]:
        return {"frames": self.frames, "error_frames": self.error_frames, "bad_frames": self.bad_frames}

    def round(self, request: Any) -> None:
        """Take one frame (waiting up to 50 ms) and publish what it carries."""
        msg = self._bus.recv(timeout=0.05)
        if msg is None:
            return
        if msg.is_error_frame:
            self.error_frames += 1
            return
        sigs = self._by_id.get(msg.arbitration_id)
        if not sigs or msg.is_remote_frame:
            return
        self.frames += 1
        now = self.now()
        data = bytes(msg.data[: msg.dlc])  # bytes past the DLC are not data
        short = len(data) < self._need[msg.arbitration_id]
        if short:
            self.bad_frames += 1
            self.last_error = (
                f"frame 0x{msg.arbitration_id:X}: {len(data)} data bytes (DLC {msg.dlc}), "
                f"the signals need {self._need[msg.arbitration_id]}"
            )
        for i, sig in sigs:
            v, q = (
                (np.nan, Quality.COMMS_LOST) if short else decode_signal(data, sig, self._burnout, self._out_of_range)
            )
            if q == Quality.GOOD:
                self._values[i] = v
            self._quality[i] = q
            self._stamp[i] = now
        self.snapshot.publish(self._values, self._quality, self._stamp)

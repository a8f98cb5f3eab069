"""The source interface: publish named signals into the frame without blocking the cycle."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from compd.core.clock import Clock
from compd.core.config import SourceConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.io.child import hosting_now
from compd.io.histogram import DurationHist
from compd.io.mailbox import Snapshot
from compd.io.ring import MessageRing
from compd.io.worker import STALL_AFTER_S, DeviceWork, IoWorker, LinkDown

if TYPE_CHECKING:
    from collections import deque

    from compd.core.probe import Probe


def check_serial_port(port: str, config_path: tuple[str | int, ...], key: str = "serial_port") -> None:
    """BadInput naming the key when a serial device path does not exist (a typo, an adapter
    not plugged in at start-up). pyserial URLs (`socket://`, `rfc2217://`, `loop://`) pass:
    their far end is checked when polled. A port that goes away later is a comms fault."""
    import os

    if "://" not in port and not os.path.exists(port):
        raise BadInput(f"no serial device {port!r}", path=(*config_path, key))


class Source(ABC):
    """A source of signals. `read` is called every cycle and must never block.

    Fast, in-process sources fill the frame directly in `read`. Slow ones (serial,
    network) subclass `PolledSource`, whose I/O worker polls beside the cycle and lets
    `read` copy the freshest sample with its time stamp.
    """

    Config: ClassVar[type[SourceConfig]] = SourceConfig

    def __init__(self, cfg: SourceConfig, base_dir: str = ".") -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.base_dir = base_dir
        # where this section sits in the config (set by the app): `open` names its keys under it
        self.config_path: tuple[str | int, ...] = ()
        self._idx = np.zeros(0, dtype=np.intp)
        # round trip of each poll (request to reply), µs: sources polled by an I/O worker
        self.poll_hist: DurationHist | None = None

    @abstractmethod
    def signal_names(self) -> list[str]:
        """The names this source publishes (fixed after construction)."""

    def bind(self, frame: Frame) -> None:
        """Remember where this source's signals live in the frame."""
        self._idx = frame.indices(self.signal_names(), what="signal")

    def bind_probes(self, inbox: deque[Probe]) -> None:
        """The config has an `adapt` section whose inbox takes probe measurements
        (compd.cycle.adapt.Probe); other sources ignore it. A source that reads them (a CNC's
        probing cycle) puts them in its `probe_ring`, which the cycle takes between cycles."""

    def probe_ring(self) -> MessageRing | None:
        """Where this source's worker puts the probes it reads (None: it reads none)."""
        return None

    def open(self, now_s: float) -> None:
        """Connect; called once before the first cycle."""

    def start_polling(self, clock: Clock) -> None:
        """Start the I/O worker that talks to the device, stamping samples with `clock`
        (the loop's); called right after `open`. Sources read in the cycle poll nothing."""

    @property
    def start_s(self) -> float | None:
        """Loop time (s) at which this source's data begins when it plays a fixed span
        (a log, a scenario); None for a live device. A sim clock starts there."""
        return None

    @property
    def end_s(self) -> float | None:
        """Loop time (s) at which this source's data ends when it plays a fixed span;
        None for a live device. A run on the sim clock without a duration stops there."""
        return None

    def sampled(self) -> bool:
        """Whether `read` has a sample from the device to copy (a poller's first poll done)."""
        return True

    @abstractmethod
    def read(self, frame: Frame, now_s: float) -> None:
        """Copy the freshest values into the frame. Never blocks."""

    def close(self) -> None:
        """Release connections and threads."""

    def get_status(self) -> dict[str, Any]:
        return {"kind": self.cfg.kind, "name": self.name}


class Poller(DeviceWork):
    """The device half of a polled source, run on its I/O worker's thread: `poll` reads the
    device once into `values` and `quality`; the round around it stamps the sample with the
    loop clock at the moment the request went out (the sample is at least that old) and
    publishes it to the source's `Snapshot`."""

    def __init__(self, n_signals: int, snapshot: Snapshot) -> None:
        super().__init__()
        self.snapshot = snapshot
        self._values = np.full(n_signals, np.nan)
        self._quality = np.full(n_signals, Quality.NO_DATA, dtype=np.uint8)
        self.poll_errors = 0

    @abstractmethod
    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        """One blocking read of the device into `values` and `quality`; a device fault is a
        quality, not an exception. When the link itself is gone, fill in what is known
        (the channels not read: COMMS_LOST), then raise LinkDown: the worker reconnects."""

    def round(self, request: Any) -> bool:
        """One poll, stamped `request` (a lockstep clock's time) or the loop clock's now;
        True when every channel answered (none COMMS_LOST)."""
        stamp = self.now() if request is None else float(request)
        lost: LinkDown | None = None
        try:
            self.poll(self._values, self._quality)
        except LinkDown as e:
            lost = e
        except Exception as e:  # a driver bug must not kill the daemon: report as comms lost
            self._quality[:] = Quality.COMMS_LOST
            self.poll_errors += 1
            self.last_error = f"poll: {type(e).__name__}: {e}"
        self.snapshot.publish(self._values, self._quality, stamp)
        if lost is not None:
            raise lost
        return not bool(np.any(self._quality == Quality.COMMS_LOST))

    def offline(self, request: Any) -> bool:
        """The link is down: every channel COMMS_LOST, stamped as a poll would be."""
        stamp = self.now() if request is None else float(request)
        self._quality[:] = Quality.COMMS_LOST
        self.snapshot.publish(self._values, self._quality, stamp)
        return False

    def counters(self) -> dict[str, Any]:
        return {"poll_errors": self.poll_errors}


class PolledSource(Source):
    """A source whose device is polled beside the cycle, by an I/O worker.

    Subclasses say how to reach the device in `make_poller` (a `Poller`, the device half:
    it runs only on the worker's thread); the worker polls every `poll_period_s` and
    reconnects with back-off (`reconnect_min_s` … `reconnect_max_s`). The cycle side only
    reads the worker's `Snapshot`: `read` copies the last completed sample and its stamp,
    never waiting. With `stale_after_s` set, `read` marks a good sample older than that
    STALE. A lockstep plant clock asks for each poll instead (`poll_now`).
    """

    poll_period_s: float = 0.1
    stale_after_s: float | None = None
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 10.0
    poll_timeout_s: float = 60.0  # how long `poll_now` waits for its poll to end
    stall_after_s: float = STALL_AFTER_S  # silence of the worker's thread that is a stall (compd.io.supervisor)
    # the poller may run in a child process (it hands the cycle nothing but its Snapshot)
    forkable: bool = True

    def __init__(self, cfg: SourceConfig, base_dir: str = ".") -> None:
        super().__init__(cfg, base_dir)
        self._snapshot = Snapshot(len(self.signal_names()))
        self._worker: IoWorker | None = None
        self.poll_hist: DurationHist = DurationHist()

    @abstractmethod
    def make_poller(self, snapshot: Snapshot) -> Poller:
        """The device half, built from the config, publishing to `snapshot`."""

    @property
    def worker(self) -> IoWorker:
        """The I/O worker that polls the device (built on first use, started by `start_polling`)."""
        if self._worker is None:
            self._worker = IoWorker(
                self.make_poller(self._snapshot),
                name=f"poll-{self.name}",
                period_s=self.poll_period_s,
                reconnect_min_s=self.reconnect_min_s,
                reconnect_max_s=self.reconnect_max_s,
                round_hist=self.poll_hist,
                stall_after_s=self.stall_after_s,
            )
        return self._worker

    def start_polling(self, clock: Clock) -> None:
        """Poll every `poll_period_s`; or, when the clock drives the polls (a lockstep plant
        clock), only when it asks (`poll_now`, between cycles)."""
        driven = clock.adopt_poller(self)
        host = hosting_now()
        self.worker.start(
            paced=not driven,
            clock=clock.now,
            process=host.process and self.forkable and not driven,
            avoid_cpus=host.cpus,
        )

    def poll_now(self, stamp: float) -> bool:
        """One poll, stamped `stamp`, and wait for it; False when the device did not answer
        (some channel COMMS_LOST). Not for the cycle: between cycles (lockstep)."""
        return bool(self.worker.request(stamp, self.poll_timeout_s))

    @property
    def polls(self) -> int:
        """Samples published (polls, and rounds while the link was down)."""
        return self._snapshot.count

    def sampled(self) -> bool:
        return self._snapshot.count > 0

    def read(self, frame: Frame, now_s: float) -> None:
        stamp = self._snapshot.copy_to(frame, self._idx)
        stale = self.stale_after_s
        if stale is not None and now_s - stamp > stale:
            q = frame.quality[self._idx]
            frame.quality[self._idx] = np.where(q == Quality.GOOD, Quality.STALE, q)

    def io_status(self) -> dict[str, Any]:
        """The worker's and the poller's counts (state, connects, errors, last_error, …)."""
        return self.worker.get_status()

    def get_status(self) -> dict[str, Any]:
        """Kind, name and the process its device I/O runs in (`io_pid`: the daemon's own
        when the worker is a thread)."""
        return {**super().get_status(), "io_pid": self.io_status().get("pid")}

    def close(self) -> None:
        if self._worker is not None:
            self._worker.stop()

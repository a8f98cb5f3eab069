"""The source interface: publish named signals into the frame without blocking the cycle."""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from compd.clock import Clock
from compd.config import SourceConfig
from compd.errors import BadInput
from compd.frame import Frame, Quality
from compd.histogram import DurationHist


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
    network) subclass `PolledSource`, which polls on its own thread and lets `read`
    copy the freshest sample with its time stamp.
    """

    Config: ClassVar[type[SourceConfig]] = SourceConfig

    def __init__(self, cfg: SourceConfig, base_dir: str = ".") -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.base_dir = base_dir
        # where this section sits in the config (set by the app): `open` names its keys under it
        self.config_path: tuple[str | int, ...] = ()
        self._idx = np.zeros(0, dtype=np.intp)
        # round trip of each poll (request to reply), µs: sources polled on their own thread
        self.poll_hist: DurationHist | None = None

    @abstractmethod
    def signal_names(self) -> list[str]:
        """The names this source publishes (fixed after construction)."""

    def bind(self, frame: Frame) -> None:
        """Remember where this source's signals live in the frame."""
        self._idx = frame.indices(self.signal_names(), what="signal")

    def open(self, now_s: float) -> None:
        """Connect; called once before the first cycle."""

    def start_polling(self, clock: Clock) -> None:
        """Start polling the device on a thread of its own, stamping samples with `clock`
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


class PolledSource(Source):
    """A source whose device is polled on its own thread (slow I/O stays off the cycle).

    Subclasses implement `poll(values, quality)` which performs one blocking
    request/response and fills the two arrays; it returns normally even on a
    device fault (by setting quality). The thread stamps each poll with the loop
    clock at the moment the request went out (the sample is at least that old), and
    `read` copies the last completed sample under a lock. With `stale_after_s` set,
    `read` marks a good sample older than that STALE.
    """

    poll_period_s: float = 0.1
    stale_after_s: float | None = None

    def __init__(self, cfg: SourceConfig, base_dir: str = ".") -> None:
        super().__init__(cfg, base_dir)
        n = len(self.signal_names())
        self._values = np.full(n, np.nan)
        self._quality = np.full(n, Quality.NO_DATA, dtype=np.uint8)
        self._stamp = -np.inf
        self._buf_values = np.full(n, np.nan)
        self._buf_quality = np.full(n, Quality.NO_DATA, dtype=np.uint8)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._clock: Clock | None = None
        self.polls = 0
        self.poll_errors = 0
        self.poll_hist: DurationHist = DurationHist()

    @abstractmethod
    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        """One blocking read of the device into `values` and `quality`."""

    def start_polling(self, clock: Clock) -> None:
        """Poll on a thread of its own; or, when the clock drives the polls (a lockstep
        plant clock), leave them to the clock, which calls `poll_now` between cycles."""
        self._clock = clock
        if clock.adopt_poller(self):
            return
        self._thread = threading.Thread(target=self._run, name=f"poll-{self.name}", daemon=True)
        self._thread.start()

    def poll_now(self, stamp: float) -> bool:
        """One poll on the caller's thread, stamped `stamp`; False when the device did not
        answer (some channel COMMS_LOST)."""
        perf = time.perf_counter_ns
        p0 = perf()
        try:
            self.poll(self._buf_values, self._buf_quality)
        except Exception:  # a driver bug must not kill the daemon: report as comms lost
            self._buf_quality[:] = Quality.COMMS_LOST
            self.poll_errors += 1
        self.poll_hist.add_ns(perf() - p0)
        with self._lock:
            self._values[:] = self._buf_values
            self._quality[:] = self._buf_quality
            self._stamp = stamp
            self.polls += 1
        return not bool(np.any(self._buf_quality == Quality.COMMS_LOST))

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            clock = self._clock
            assert clock is not None  # set by start_polling
            self.poll_now(clock.now())
            rest = self.poll_period_s - (time.monotonic() - t0)
            if rest > 0:
                self._stop.wait(rest)

    def sampled(self) -> bool:
        return self.polls > 0

    def read(self, frame: Frame, now_s: float) -> None:
        with self._lock:
            frame.values[self._idx] = self._values
            frame.quality[self._idx] = self._quality
            frame.stamp_s[self._idx] = self._stamp
        stale = self.stale_after_s
        if stale is not None and now_s - self._stamp > stale:
            q = frame.quality[self._idx]
            frame.quality[self._idx] = np.where(q == Quality.GOOD, Quality.STALE, q)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

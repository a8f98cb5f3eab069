"""Observe mode: wrap the configured sink so the loop runs in full but the output stays disabled.

Used for commissioning (`observe: true` or `compd run --observe`): sources,
model, guard and codec run every cycle and are logged, the device is opened and
its heartbeat kept, but every write carries the safe word (every enable bit
off). The user compares predictions with measurements before the first real
correction reaches the machine.

A device found holding a correction when observe mode starts (an earlier run killed while it
compensated) is not dropped at once: the sink takes it back to 0 at the guard's
`ramp_um_per_s` (the word one LSB at a time), then holds the safe word.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from compd.codec import Encoder
from compd.io.worker import LinkState
from compd.sinks.base import Sink

if TYPE_CHECKING:
    from compd.models.base import Model


class ObserveSink(Sink):
    """Delegates to `inner`, always with the word 0 and every axis disabled."""

    def __init__(self, inner: Sink, ramp_um_per_s: float = 1.0, deadband_um: float = 1.0) -> None:
        super().__init__(inner.cfg, inner.base_dir)
        self.inner = inner
        self.axes, self.lsb_um = list(inner.axes), inner.lsb_um
        self.would_write = 0
        self.ramp_um_per_s = ramp_um_per_s
        self.deadband_um = deadband_um
        self.outputs: list[str] = list(inner.axes)
        # what the device held at a sync, ramped to 0: per model output (µm), and the word of it
        self._out = np.zeros(0)
        self._on = np.zeros(0, dtype=bool)
        self._enc = Encoder(max(inner.lsb_um, 1e-6), deadband_um, ramp_um_per_s)
        self._slots: list[int] = []
        self._last_s = math.nan
        self._ramping = False
        self._bind_outputs(self.outputs)

    def bind(self, axes: list[str], lsb_um: float) -> None:
        super().bind(axes, lsb_um)
        self.inner.bind(axes, lsb_um)
        self._enc = Encoder(lsb_um, self.deadband_um, self.ramp_um_per_s)
        self._bind_outputs(self.outputs if self.outputs else list(axes))

    def bind_model(self, model: Model) -> None:
        self.inner.bind_model(model)
        self._bind_outputs(list(model.outputs))

    def _bind_outputs(self, outputs: list[str]) -> None:
        self.outputs = outputs
        self._out = np.zeros(len(outputs))
        self._on = np.zeros(len(outputs), dtype=bool)
        self._slots = [outputs.index(a) if a in outputs else -1 for a in self.axes]

    def sync(self, now_s: float) -> bool:
        """The inner sink's: what the device held is where the ramp to 0 starts."""
        if not self.inner.sync(now_s):
            return False
        held = self.inner.held_um()
        for i, name in enumerate(self.outputs):
            self._out[i] = held.get(name, 0.0)
        for slot, name in enumerate(self.axes):
            self._enc.seed(slot, held.get(name, 0.0))
        self._last_s = now_s
        self._ramping = bool(np.any(self._out != 0.0))
        self.syncs += 1
        return True

    def held_um(self) -> dict[str, float]:
        return self.inner.held_um()

    def synced(self) -> bool:
        return self.inner.synced()

    def await_held(self, timeout_s: float) -> bool:
        return self.inner.await_held(timeout_s)

    def open(self, now_s: float) -> None:
        self.inner.open(now_s)

    def device_key(self) -> Any:
        return self.inner.device_key()

    def link_state(self) -> LinkState:
        return self.inner.link_state()

    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        self.would_write = word
        changed = self.writes == 0
        if self._ramping:  # a correction found at the device: to 0 at the ramp rate, never a step
            dt = now_s - self._last_s if self._last_s == self._last_s else 0.0
            self._last_s = now_s
            step = self.ramp_um_per_s * max(dt, 0.0)
            out = self._out
            for i in range(out.shape[0]):
                v = float(out[i])
                out[i] = v - step if v > step else (v + step if v < -step else 0.0)
            np.not_equal(out, 0.0, out=self._on)
            s0, s1 = (self._slots + [-1, -1])[:2]
            c1 = float(out[s0]) if s0 >= 0 else 0.0
            c2 = float(out[s1]) if s1 >= 0 else 0.0
            changed = self._enc.update(c1, c2, c1 != 0.0, c2 != 0.0, max(dt, 0.0)) or changed
            self._ramping = bool(self._on.any()) or self._enc.word != 0
        self.inner.write(self._enc.word, self._out, self._on, changed, now_s)
        self.writes += 1

    def flush(self, timeout_s: float) -> bool:
        return self.inner.flush(timeout_s)

    def safe(self) -> bool:
        return self.inner.safe()

    def applied_um(self, out: np.ndarray) -> None:
        self.inner.applied_um(out)

    def close(self) -> None:
        self.inner.close()

    def device_info(self) -> dict[str, Any]:
        return self.inner.device_info()

    def get_status(self) -> dict[str, Any]:
        """The inner sink's status; `word` is what it writes (always 0x0000), `would_write` the
        word the loop computed and held back."""
        return {
            **self.inner.get_status(),
            "observe": True,
            "word": "0x0000",
            "would_write": f"0x{self.would_write:04X}",
        }

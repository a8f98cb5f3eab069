"""Observe mode: wrap the configured sink so the loop runs in full but the output stays disabled.

Used for commissioning (`observe: true` or `compd run --observe`): sources,
model, guard and codec run every cycle and are logged, the device is opened and
its heartbeat kept, but every write carries the safe word (every enable bit
off). The user compares predictions with measurements before the first real
correction reaches the machine.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from compd.sinks.base import LinkState, Sink

if TYPE_CHECKING:
    from compd.models.base import Model


class ObserveSink(Sink):
    """Delegates to `inner`, always with the word 0 and every axis disabled."""

    def __init__(self, inner: Sink) -> None:
        super().__init__(inner.cfg, inner.base_dir)
        self.inner = inner
        self.axes, self.lsb_um = list(inner.axes), inner.lsb_um
        self.would_write = 0
        self._zeros = np.zeros(0)
        self._off = np.zeros(0, dtype=bool)

    def bind(self, axes: list[str], lsb_um: float) -> None:
        super().bind(axes, lsb_um)
        self.inner.bind(axes, lsb_um)

    def bind_model(self, model: Model) -> None:
        self.inner.bind_model(model)

    def open(self, now_s: float) -> None:
        self.inner.open(now_s)

    def device_key(self) -> Any:
        return self.inner.device_key()

    def link_state(self) -> LinkState:
        return self.inner.link_state()

    def write(
        self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float
    ) -> None:
        if self._zeros.shape != corr_um.shape:
            self._zeros = np.zeros(corr_um.shape)
            self._off = np.zeros(enable.shape, dtype=bool)
        self.would_write = word
        self.inner.write(0, self._zeros, self._off, self.writes == 0, now_s)
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
        return {**self.inner.get_status(), "observe": True, "word": "0x0000",
                "would_write": f"0x{self.would_write:04X}"}

"""PCI-1756 digital-output sink (paper 002, SPEC §4.1): the word on two DO bytes, plus a heartbeat."""

from __future__ import annotations

from typing import Any, Literal, Protocol

import numpy as np
from pydantic import Field, model_validator

from compd.codec import word_to_um
from compd.config import SinkConfig
from compd.sinks.base import Sink


class DoCard(Protocol):
    """What the sink needs of a PCI-1756 driver."""

    def write_do_word(self, port: int, value: int) -> None: ...
    def write_do_bit(self, bit: int, on: bool) -> None: ...
    def read_do_word(self, port: int) -> int: ...


class Pci1756Config(SinkConfig):
    """The word on DO bytes `word_port`, `word_port`+1 (low byte first); heartbeat on a spare bit."""

    device: Literal["emulated"] = Field(
        "emulated", description="driver: the in-process card emulator"
    )
    word_port: int = Field(0, ge=0, le=2, description="DO byte offset of the word's low byte")
    heartbeat_bit: int | None = Field(
        16, ge=0, le=31, description="DO bit toggled every cycle; none = no heartbeat"
    )

    @model_validator(mode="after")
    def _heartbeat_outside_word(self) -> Pci1756Config:
        hb = self.heartbeat_bit
        if hb is not None and 8 * self.word_port <= hb < 8 * self.word_port + 16:
            raise ValueError("heartbeat_bit must not be one of the word's 16 bits")
        return self


class Pci1756Sink(Sink):
    """Writes the word when it changes and toggles the heartbeat bit every cycle."""

    Config = Pci1756Config

    def __init__(self, cfg: Pci1756Config, base_dir: str = ".", card: DoCard | None = None) -> None:
        super().__init__(cfg, base_dir)
        if card is None:
            from hil_sim.devices.pci1756 import Pci1756Card

            card = Pci1756Card()
        self.card = card
        self._heartbeat = False
        self.word = 0

    def write(
        self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float
    ) -> None:
        if changed or self.writes == 0:
            self.card.write_do_word(self.cfg.word_port, word)
            self.word = word
        self.writes += 1
        if self.cfg.heartbeat_bit is not None:
            self._heartbeat = not self._heartbeat
            self.card.write_do_bit(self.cfg.heartbeat_bit, self._heartbeat)

    def safe(self) -> None:
        self.card.write_do_word(self.cfg.word_port, 0)
        self.word = 0

    def applied_um(self, out: np.ndarray) -> None:
        c1, c2 = word_to_um(self.card.read_do_word(self.cfg.word_port), self.lsb_um)
        out[0] = c1
        if out.shape[0] > 1:
            out[1] = c2

    def get_status(self) -> dict[str, Any]:
        return {**super().get_status(), "word": f"0x{self.word:04X}"}

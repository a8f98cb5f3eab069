"""PCI-1756 digital-output sink (paper 002): the word on two DO bytes, plus a heartbeat.

The card's outputs latch: a word written by an earlier run stays on the lines after compd
ends (killed, or the watchdog's SIGABRT). At its open, and whenever the link to the card is
restored, the sink reads the DO lines back (the PCI-1756 reads back its output latch; the
card over Modbus: the X registers the DO bytes were written to) before it writes anything,
and the guard and the word start from the word found there (compd.sinks.base, "what the
device holds"): the word walks from it one LSB a cycle, never jumps to 0 at a start."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.codec import MAX_MAG, byte_to_um, word_to_um
from compd.core.config import SinkConfig
from compd.io.modbus_link import ModbusLink
from compd.io.worker import LinkState
from compd.plc.pci1756 import DoCard, Pci1756Card
from compd.sinks.base import SAFE_TIMEOUT_S, Sink


class Pci1756Config(SinkConfig):
    """The word on DO bytes `word_port`, `word_port`+1 (low byte first); heartbeat on a spare bit."""

    device: Literal["emulated", "modbus"] = Field(
        "emulated",
        description="driver: the software PLC's card in process, or its DO bytes sent over Modbus TCP"
        " to the X inputs of a PMC in another process",
    )
    host: str = Field("127.0.0.1", description="modbus: the PMC's address")
    port: int = Field(502, ge=1, le=65535, description="modbus: the PMC's port")
    device_id: int = Field(1, ge=0, le=247)
    x_register: int = Field(
        0, ge=0, le=65532, description="modbus: register of the X byte wired to DO0 (4 DO bytes follow)"
    )
    strobe_bit: int | None = Field(
        None, ge=0, le=31, description="DO bit toggled with every new word (the PMC latches on its edge)"
    )
    word_port: int = Field(0, ge=0, le=2, description="DO byte offset of the word's low byte")
    heartbeat_bit: int | None = Field(16, ge=0, le=31, description="DO bit toggled every cycle; none = no heartbeat")

    @model_validator(mode="after")
    def _heartbeat_outside_word(self) -> Pci1756Config:
        hb = self.heartbeat_bit
        word_bits = range(8 * self.word_port, 8 * self.word_port + 16)
        if hb is not None and hb in word_bits:
            raise ValueError("heartbeat_bit must not be one of the word's 16 bits")
        sb = self.strobe_bit
        if sb is not None and (sb in word_bits or sb == hb):
            raise ValueError("strobe_bit must be a spare bit (not the word's, not the heartbeat)")
        return self


class ModbusDoCard(DoCard):
    """The card's DO lines as seen by a PMC elsewhere: every write sends DO bytes 0–3 to
    four X registers over Modbus TCP (queued; the cycle never waits on the network)."""

    def __init__(self, host: str, port: int, device_id: int = 1, x_register: int = 0) -> None:
        self._do = bytearray(4)
        self.x_register = x_register
        # the four X registers the DO bytes are written to are read back at every connect
        self.link = ModbusLink(host, port, device_id=device_id, name="pci1756", sync=[(x_register, 4)])

    def start(self) -> None:
        self.link.start()

    def held(self) -> tuple[int, int] | None:
        got = self.link.held()
        if got is None:
            return None
        epoch, regs = got
        return epoch, sum((r & 0xFF) << (8 * k) for k, r in enumerate(regs[:4]))

    def accept(self, epoch: int, lines: int) -> None:
        """The lines read back are the card's from now on (the next write sends them with its change)."""
        self._do[:] = (lines & 0xFFFFFFFF).to_bytes(4, "little")
        self.link.accept(epoch)

    def synced(self) -> bool:
        return self.link.synced()

    def await_held(self, timeout_s: float) -> bool:
        return self.link.await_held(timeout_s)

    def read_do(self) -> int:
        return int.from_bytes(self._do, "little")

    def _push(self) -> None:
        self.link.submit(self.x_register, list(self._do))

    def write_do_word(self, port: int, value: int) -> None:
        self._do[port] = value & 0xFF
        self._do[port + 1] = (value >> 8) & 0xFF
        self._push()

    def write_do_bit(self, bit: int, on: bool) -> None:
        if on:
            self._do[bit // 8] |= 1 << (bit % 8)
        else:
            self._do[bit // 8] &= ~(1 << (bit % 8)) & 0xFF
        self._push()

    def read_do_word(self, port: int) -> int:
        return self._do[port] | (self._do[port + 1] << 8)

    def link_state(self) -> LinkState:
        """The link's; `connecting` while it is up but the lines not yet read back."""
        st = self.link.state
        return "connecting" if st == "up" and not self.link.synced() else st  # type: ignore[return-value]

    def flush(self, timeout_s: float) -> bool:
        return self.link.drain(timeout_s)

    def ensure_serving(self) -> bool:
        return self.link.ensure_serving()

    def close(self) -> None:
        self.link.stop()


class Pci1756Sink(Sink):
    """Writes the word when it changes and toggles the heartbeat bit every cycle."""

    Config = Pci1756Config

    def __init__(self, cfg: Pci1756Config, base_dir: str = ".", card: DoCard | None = None) -> None:
        super().__init__(cfg, base_dir)
        self.cfg: Pci1756Config = cfg
        if card is None and cfg.device == "modbus":
            card = ModbusDoCard(cfg.host, cfg.port, cfg.device_id, cfg.x_register)
        elif card is None:
            card = Pci1756Card()
        self.card = card
        self._heartbeat = False
        self._strobe = False
        self.word = 0
        self._fresh = True  # the next write sends the word (the first after a sync)

    def device_key(self) -> Any:
        return ("modbus", self.cfg.host, self.cfg.port) if self.cfg.device == "modbus" else None

    def link_state(self) -> LinkState:
        """The card over Modbus: its link (`connecting` while up but the lines not yet read back);
        a card in this process (emulated, a driver): up."""
        return self.card.link_state()

    def open(self, now_s: float) -> None:
        """Connect; nothing is written until the DO lines are read back (`sync`)."""
        self.card.start()

    def sync(self, now_s: float) -> bool:
        """The DO lines read back on a new connection: the word on them is where the guard and the
        word start (`held_um`), and the heartbeat and strobe go on from their levels there."""
        got = self.card.held()
        if got is None:
            return False
        epoch, lines = got
        self.card.accept(epoch, lines)
        cfg = self.cfg
        self.word = (lines >> (8 * cfg.word_port)) & 0xFFFF
        if cfg.heartbeat_bit is not None:
            self._heartbeat = bool(lines >> cfg.heartbeat_bit & 1)
        if cfg.strobe_bit is not None:
            self._strobe = bool(lines >> cfg.strobe_bit & 1)
        c1, c2 = word_to_um(self.word, self.lsb_um)
        self._held_um = dict(zip(self.axes, (c1, c2), strict=False))
        self._fresh = True
        self.syncs += 1
        return True

    def synced(self) -> bool:
        return self.card.synced()

    def await_held(self, timeout_s: float) -> bool:
        return self.card.await_held(timeout_s)

    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        if not self.card.synced():  # the lines not yet read back: nothing is written
            self.writes += 1
            return
        if changed or self._fresh:
            self._fresh = False
            self.card.write_do_word(self.cfg.word_port, word)
            self.word = word
            if self.cfg.strobe_bit is not None:
                self._strobe = not self._strobe
                self.card.write_do_bit(self.cfg.strobe_bit, self._strobe)
        self.writes += 1
        if self.cfg.heartbeat_bit is not None:
            self._heartbeat = not self._heartbeat
            self.card.write_do_bit(self.cfg.heartbeat_bit, self._heartbeat)

    def safe(self) -> bool:
        """Word 0x0000 (every enable bit off) at once: the CNC drops the correction. Through a
        fresh link when the running one's worker is gone, from the lines read back there."""
        if not self.syncs:
            return True  # nothing was ever written to the card on this sink: nothing of ours to take back
        self.card.ensure_serving()
        if not self.resync(SAFE_TIMEOUT_S, 0.0):
            return False  # the card does not answer: nothing can reach it
        self.card.write_do_word(self.cfg.word_port, 0)
        self.word = 0
        if self.cfg.strobe_bit is not None:
            self._strobe = not self._strobe
            self.card.write_do_bit(self.cfg.strobe_bit, self._strobe)
        return self.card.flush(SAFE_TIMEOUT_S)

    def flush(self, timeout_s: float) -> bool:
        return self.card.flush(timeout_s)

    def close(self) -> None:
        self.card.close()

    def applied_um(self, out: np.ndarray) -> None:
        c1, c2 = word_to_um(self.card.read_do_word(self.cfg.word_port), self.lsb_um)
        out[0] = c1
        if out.shape[0] > 1:
            out[1] = c2

    def commanded_um(self, out: np.ndarray) -> None:
        """The word last written, decoded (the card's lines hold it as soon as it is written)."""
        c1, c2 = word_to_um(self.word, self.lsb_um)
        out[0] = c1
        if out.shape[0] > 1:
            out[1] = c2

    def write_rows(
        self,
        t_s: np.ndarray,
        words: np.ndarray,
        changed: np.ndarray,
        corr_um: np.ndarray,
        enable: np.ndarray,
        applied_um: np.ndarray,
        commanded_um: np.ndarray,
        terms: list[list[tuple[float, float]] | None] | None = None,
        positions_mm: np.ndarray | None = None,
    ) -> None:
        """`Sink.write_rows`; on the software PLC's card only the rows with a new word are
        written (the heartbeat then toggled as often as the rows between would have): the
        card's lines hold each word from its row on, and the word is what they apply."""
        n = len(t_s)
        if not isinstance(self.card, Pci1756Card) or type(self).write is not Pci1756Sink.write or n == 0:
            super().write_rows(t_s, words, changed, corr_um, enable, applied_um, commanded_um, terms, positions_mm)
            return
        rows = np.flatnonzero(changed)
        if self._fresh and (rows.size == 0 or rows[0] != 0):
            rows = np.r_[0, rows]
        for r in rows.tolist():
            self.write(int(words[r]), corr_um[r], enable[r], bool(changed[r]), float(t_s[r]))
        rest = n - rows.size
        self.writes += rest
        if self.cfg.heartbeat_bit is not None and rest % 2:
            self._heartbeat = not self._heartbeat
            self.card.write_do_bit(self.cfg.heartbeat_bit, self._heartbeat)
        written = np.zeros(n, dtype=bool)
        written[rows] = True
        held = np.asarray(words, dtype=np.int64)[np.maximum.accumulate(np.where(written, np.arange(n), 0))]
        table = np.array([byte_to_um(b, self.lsb_um) for b in range(256)])
        um = np.column_stack([table[held >> 8], table[held & 0xFF]])
        applied_um[:] = um[:, : applied_um.shape[1]]
        commanded_um[:] = um[:, : commanded_um.shape[1]]

    @classmethod
    def in_process_config(cls, cfg: SinkConfig) -> SinkConfig:
        """The software PLC's card in process, with this section's word port, strobe and heartbeat."""
        return cfg.model_copy(update={"device": "emulated"})

    def device_info(self) -> dict[str, Any]:
        """The word on the DO lines: the codec's LSB, full scale 63 LSB, no rate limit of its own."""
        cfg = self.cfg
        where = "in process" if cfg.device == "emulated" else f"over modbus at {cfg.host}:{cfg.port}"
        return {
            "device": f"pci1756 card {where}",
            "resolution_um": self.lsb_um,
            "max_abs_um": MAX_MAG * self.lsb_um,
            "max_rate_um_per_s": None,
        }

    def get_status(self) -> dict[str, Any]:
        return {**super().get_status(), "word": f"0x{self.word:04X}"}

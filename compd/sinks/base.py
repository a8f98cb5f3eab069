"""The sink interface: hand the CNC the word (or corrections) every cycle; know the safe output."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Hashable
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from compd.core.config import SinkConfig
from compd.io.worker import LinkState

if TYPE_CHECKING:
    from compd.io.modbus_link import ModbusLink
    from compd.models.base import Model
    from compd.plc.link import VirtualLink

# What a sink knows of its connection to the machine (`Sink.link_state`):
#   up          the device answers (or it is in process: nothing can be lost on the way)
#   connecting  opened, no answer yet
#   down        the device does not answer: nothing the loop computes reaches the machine
#   closed      not open
SAFE_TIMEOUT_S = 2.0  # how long the safe output waits for each write to be acknowledged


class Sink(ABC):
    """Where corrections go.

    `write` is called every cycle with the encoded word, the guarded per-axis
    corrections (µm) and enable flags, and whether the word changed; a sink does
    device I/O only when it must (a changed value, a heartbeat). `safe` puts the
    output in its safe state (every enable bit off) and must work at any time,
    including from a signal handler's exit path. `applied_um` reports what the
    machine actually applies, as far as the sink can know it. `link_state` says
    whether what it writes reaches the machine at all.
    """

    Config: ClassVar[type[SinkConfig]] = SinkConfig
    # the sink sends the model's linear terms (`Model.linear_terms`) with each write
    sends_linear_terms: ClassVar[bool] = False

    def __init__(self, cfg: SinkConfig, base_dir: str = ".") -> None:
        self.cfg = cfg
        self.base_dir = base_dir
        # where this section sits in the config (set by the app): `open` names its keys under it
        self.config_path: tuple[str | int, ...] = ()
        self.axes: list[str] = []
        self.lsb_um = 1.0
        self.writes = 0
        # the link to the device (sinks that write registers): a thread that writes over the
        # network, whose write round trips and output latency are the bench's I/O statistics,
        # or the same interface to a device of the software PLC in this process
        self.link: ModbusLink | VirtualLink | None = None
        self.syncs = 0  # times the sink learned what its device holds (`sync`)
        self._held_um: dict[str, float] = {}  # ... and what it held then, by axis

    def bind(self, axes: list[str], lsb_um: float) -> None:
        """The word's axes (high byte first) and the codec's LSB."""
        self.axes = list(axes)
        self.lsb_um = lsb_um

    def bind_model(self, model: Model) -> None:
        """The model whose outputs the sink is handed (sinks that speak per-axis values)."""

    def open(self, now_s: float) -> None:
        """Connect to the device; called once before the first cycle. Writes nothing that could
        move an axis: what the device holds is not known yet (`sync`)."""

    # ------------------------------------------------------------ what the device holds
    # A sink never assumes what its device applies: compd's own earlier run may have been
    # killed while the device held a correction, or the device restarted and holds 0. At its
    # open, and whenever its link to the device is restored, the sink reads back what the device
    # applies (`held_um`) before it writes anything that could move an axis, and steps from
    # there; the loop starts the guard and the word from it too (`Loop.sync_output`), so the
    # first word of every start, reload and link restart is within one step of the machine.
    def sync(self, now_s: float) -> bool:
        """Every cycle, before the guard (never waits): True in the cycle the sink has just learned
        what its device holds — at its open, and after its link to the device was restored — and
        reckons from it from now on; `held_um` then says what. The base reads its link's held
        block (compd.io.modbus_link: read at every connect, before anything is sent) and hands
        it to `take_held`."""
        link = self.link
        if link is None:
            return False
        got = link.held()
        if got is None:
            return False
        epoch, regs = got
        link.accept(epoch)  # what was queued before is dropped; what is submitted from now on is sent
        self.take_held(regs, now_s)
        self.syncs += 1
        return True

    def resync(self, timeout_s: float, now_s: float) -> bool:
        """Outside the cycle (the safe output, a test): make sure the sink knows what its device
        holds on the current connection, waiting up to `timeout_s` for the link's held block;
        False when it cannot (nothing that could move an axis may be written then)."""
        if self.synced():
            return True
        if not self.await_held(timeout_s):
            return False
        self.sync(now_s)
        return self.synced()

    def take_held(self, regs: list[int], now_s: float) -> None:
        """The held block of a new connection (the registers of the link's sync ranges): reckon
        from it, and say it in `held_um`. Sinks with a link to a device override this."""

    def held_um(self) -> dict[str, float]:
        """What the device applied when the sink last synced (`sync` True), µm by axis name (the
        axes the device reports); the guard and the word start there."""
        return dict(self._held_um)

    def await_held(self, timeout_s: float) -> bool:
        """Outside the cycle (replay, output-test, a lockstep clock before it releases the plant,
        the safe output): wait until the sink can sync (`sync` will say True, or it has already);
        False after `timeout_s` (the device does not answer)."""
        return self.link is None or self.link.await_held(timeout_s)

    def synced(self) -> bool:
        """Whether the sink knows what its device holds on the current connection: what it
        submits now is sent (before, it writes nothing that could move an axis)."""
        return self.link is None or self.link.synced()

    def device_key(self) -> Hashable | None:
        """What outside device this sink holds (e.g. a Modbus host and port), or None when
        it holds none (an in-process device). A config reload never opens a second sink on
        a device the running one holds: the old sink is released first."""
        return None

    def link_state(self) -> LinkState:
        """Whether what `write` sends reaches the machine (see LINK_STATES): the link's state,
        `connecting` while it is up but what the device holds is not yet read back (`sync`)."""
        if self.link is None:
            return "closed"
        st = self.link.state
        return "connecting" if st == "up" and not self.link.synced() else st  # type: ignore[return-value]

    @abstractmethod
    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        """Hand the CNC this cycle's output."""

    def settle(self, now_s: float) -> None:
        """Let the device act on what was written by loop time `now_s` before `applied_um`
        is read (replay: the PLC scans, a write over the network is acknowledged). Sinks
        whose device acts at once have nothing to wait for."""

    @abstractmethod
    def safe(self) -> bool:
        """Emit the safe output (enable bits off, the correction walked back to zero where
        the device asks for steps), through a fresh link when the running one's worker is
        gone; True when the device acknowledged it (within `SAFE_TIMEOUT_S` per write), or when
        the sink never synced (nothing of compd's was written: nothing to take back). The walk
        starts from what the device holds, read back when the link is new (False when it cannot
        be read: nothing that could move an axis is written blind)."""

    @abstractmethod
    def applied_um(self, out: np.ndarray) -> None:
        """Write what the machine applies now, per axis (µm), into `out`."""

    def set_positions(self, positions_mm: np.ndarray) -> None:
        """Replay: where each of the model's output axes stands now (mm, NaN unknown), for a device of
        the software PLC in this process that applies a correction depending on it (the Siemens
        NC's tanβ·(P − P0)); a real device knows its axes' positions. Default: nothing to tell."""

    def commanded_um(self, out: np.ndarray) -> None:
        """Write what the machine is commanded to apply now, per axis of the word (µm): the
        word's correction, or the device's target; NaN where the sink cannot say. Beside
        `applied_um` it shows the device trailing its command."""
        out[:] = np.nan

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
        """Replay: at each row i, `write` row i's output (word, per-axis corrections and enable
        flags of the model's outputs) at loop time t_s[i], `settle`, and read what the machine
        applies and is commanded into row i of `applied_um` and `commanded_um` (rows × the
        word's axes). `terms`: the model's linear terms at each row, for a sink that sends them;
        `positions_mm`: where each of the model's output axes stood at each row (rows × outputs,
        NaN unknown), told to the device first (`set_positions`).

        This is the reference; a sink whose device is in this process may skip the rows in
        which nothing can change, with the same result."""
        applied = np.zeros(applied_um.shape[1])
        commanded = np.zeros(commanded_um.shape[1])
        for i, now in enumerate(t_s.tolist()):
            if positions_mm is not None:
                self.set_positions(positions_mm[i])
            self.write(int(words[i]), corr_um[i], enable[i], bool(changed[i]), now)
            self.settle(now)
            self.applied_um(applied)
            self.commanded_um(commanded)
            applied_um[i] = applied
            commanded_um[i] = commanded

    def flush(self, timeout_s: float) -> bool:
        """Wait until every write so far has been acknowledged by the device (lockstep runs:
        the plant steps only after that); False after `timeout_s`. In process: nothing to wait for."""
        return True

    def close(self) -> None:
        """Release the device (after `safe`)."""

    @classmethod
    def in_process_config(cls, cfg: SinkConfig) -> SinkConfig:
        """`cfg` for this sink's own device of the software PLC in this process, with the
        same layout, resolution and limits (replay); `cfg` when it is in process already."""
        return cfg

    def device_info(self) -> dict[str, Any]:
        """What device this sink drives and how finely and how far it can move an axis:
        `device` (a name, with "in process" or the address), `resolution_um` (the smallest
        change that reaches the machine), `max_abs_um` (the device's largest correction, None
        when only the guard clamps), `max_rate_um_per_s` (the device's own rate limit, or None)."""
        return {"device": self.cfg.kind, "resolution_um": None, "max_abs_um": None, "max_rate_um_per_s": None}

    def get_status(self) -> dict[str, Any]:
        return {
            "kind": self.cfg.kind,
            "writes": self.writes,
            "link": self.link_state(),
            "syncs": self.syncs,
            "held_um": self.held_um(),
        }

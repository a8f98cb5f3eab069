"""fanuc_pmc sink: splits large changes under the PMC's step limit, in process and over Modbus TCP."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from compd.codec import encode, word_from_codes
from compd.io.device_time import DeviceTime
from compd.plc.fanuc_pmc import FanucPmc
from compd.sinks.base import Sink
from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink, step_toward
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.scan import PmcScanThread

Z = np.zeros(2)
EN = np.ones(2, dtype=bool)


def test_step_toward():
    assert step_toward([0, 0], [12, -3], 5) == [5, -3]
    assert step_toward([5, -3], [12, -3], 5) == [10, -3]


@pytest.mark.parametrize("mode", ["word", "shift"])
def test_in_process_walks_to_target_without_alarm(mode):
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode=mode, max_step_um=5, step_limit_um=10))
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0)  # what the PMC applies, read back before anything is written
    word = encode(30, -20)
    applied = []
    out = np.zeros(2)
    for k in range(200):  # 2 ms cycles, simulated
        t = k * 0.002
        sink.write(word, Z, EN, k == 0, t)
        sink.settle(t)
        sink.applied_um(out)
        applied.append(out.copy())
    a = np.array(applied)
    assert a[-1].tolist() == [30.0, -20.0]
    assert np.max(np.abs(np.diff(a, axis=0))) <= 5.0
    assert sink.get_status()["alarm"] == 0
    sink.safe()
    sink.applied_um(out)
    assert out.tolist() == [0.0, 0.0]
    assert sink.get_status()["alarm"] == 0


def test_config_rejects_step_above_in_process_limit():
    with pytest.raises(ValueError, match="step_limit_um"):
        FanucPmcConfig(kind="fanuc_pmc", max_step_um=20, step_limit_um=10)


def _run_remote(sink: FanucPmcSink, word: int, seconds: float) -> None:
    t0 = time.monotonic()
    first = True
    while time.monotonic() - t0 < seconds:
        sink.write(word, Z, EN, first, time.monotonic())
        first = False
        time.sleep(0.002)


def test_over_modbus_tcp_against_scanning_pmc():
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            cfg = FanucPmcConfig(kind="fanuc_pmc", host="127.0.0.1", port=srv.port, max_step_um=5)
            sink = FanucPmcSink(cfg)
            sink.bind(["x1", "x2"], 1.0)
            sink.open(time.monotonic())
            try:
                assert sink.resync(5.0, time.monotonic())  # what the PMC applies, read back over Modbus
                _run_remote(sink, encode(25, -12), 0.6)
                sink.settle(0.0)
                time.sleep(0.05)
                assert pmc.applied_um() == [25.0, -12.0]
                assert pmc.alarms() == 0
                out = np.zeros(2)
                sink.applied_um(out)  # from the status the link reads back
                assert out.tolist() == [25.0, -12.0]
                sink.safe()
                time.sleep(0.05)
                assert pmc.applied_um() == [0.0, 0.0] and pmc.alarms() == 0
            finally:
                sink.close()
    finally:
        scan.stop()


def test_without_splitting_the_pmc_alarms():
    """The reason for max_step_um: one 25 µm jump trips the PMC's 10 µm limit."""
    pmc = FanucPmc(step_limit_um=10)
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", max_step_um=63, step_limit_um=63), pmc=pmc)
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0)  # what the PMC applies, read back before anything is written
    pmc.write_registers(300, [10])  # D0: the machine's real limit
    sink.write(encode(25, 0), Z, EN, True, 0.05)
    sink.settle(0.05)
    assert pmc.alarms() == 0b01 and pmc.applied_um() == [0.0, 0.0]


class _Spy(FanucPmc):
    """Records (scan count, axis, change of the applied shift) at every scan that changes it."""

    def __init__(self, **kw) -> None:  # noqa: ANN003
        super().__init__(**kw)
        self.changes: list[tuple[int, int, float]] = []

    def scan(self) -> bool:
        before = self.applied_um()
        changed = super().scan()
        for a, (b, c) in enumerate(zip(before, self.applied_um(), strict=True)):
            if c != b:
                self.changes.append((self.scans, a, c - b))
        return changed


@pytest.mark.parametrize("mode", ["word", "shift"])
def test_in_process_a_call_after_dt_takes_the_steps_dt_allows(mode):
    """The PMC on the loop's time: a call 0.1 s after the last (the sync at 0) makes the six 5 µm
    steps min_update_s (0.02 s) allows in [0, 0.1] s, two scans or more apart, and the next call
    the rest."""
    pmc = _Spy(step_limit_um=10)
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode=mode, max_step_um=5, min_update_s=0.02), pmc=pmc)
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0)  # what the PMC applies, read back before anything is written
    out = np.zeros(2)
    sink.write(encode(40, -12), Z, EN, True, 0.1)
    sink.settle(0.1)
    sink.applied_um(out)
    assert out.tolist() == [30.0, -12.0]
    sink.write(encode(40, -12), Z, EN, False, 1.0)
    sink.settle(1.0)
    sink.applied_um(out)
    assert out.tolist() == [40.0, -12.0]
    steps = [c for c in pmc.changes if c[1] == 0]
    assert [c[2] for c in steps] == [5.0] * 8
    assert min(b[0] - a[0] for a, b in zip(steps, steps[1:], strict=False)) >= 2
    assert pmc.alarms() == 0 and sink.time.now_s < 1.0 + 0.05  # the PMC's time a few scans past the loop's


class _OwnClock(DeviceTime):
    """A PMC on its own clock (as over Modbus), here in process: waiting is an error (the cycle never waits)."""

    def wait(self, dt_s: float) -> None:
        raise AssertionError(f"the cycle waited {dt_s} s")


def test_on_its_own_clock_a_call_makes_one_step_and_never_waits():
    """The live daemon's PMC (its own clock): one step of max_step_um per call at most, however
    long since the last call, and the call never waits."""
    pmc = FanucPmc(step_limit_um=10)
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", max_step_um=5, min_update_s=0.02), pmc=pmc)
    sink.time = _OwnClock()
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0)  # what the PMC applies, read back before anything is written
    sink.write(encode(40, 0), Z, EN, True, 5.0)
    assert sink.sent_lsb == [5, 0] and sink.updates == 1  # one step (the open writes nothing)
    sink.write(encode(40, 0), Z, EN, False, 5.01)  # before min_update_s: nothing
    assert sink.sent_lsb == [5, 0]
    sink.write(encode(40, 0), Z, EN, False, 60.0)
    assert sink.sent_lsb == [10, 0]


@pytest.mark.parametrize("mode", ["word", "shift"])
def test_write_rows_equals_writing_row_by_row(mode):
    """`write_rows` (the rows where nothing can change skipped) gives the applied and commanded
    shift of write, settle and read at every row, and leaves the PMC alike."""
    rng = np.random.default_rng(3)
    n = 2000
    t = np.cumsum(rng.choice([0.002, 0.5, 1.0, 10.0], n, p=[0.2, 0.3, 0.4, 0.1]))
    codes = np.clip(np.cumsum(rng.choice([0, 0, 0, 0, 1, -1, 12, -9], (n, 2)), axis=0), -63, 63)
    words = np.array([word_from_codes(int(a), int(b)) for a, b in codes])
    changed = np.r_[True, words[1:] != words[:-1]]
    corr, en = np.zeros((n, 2)), np.ones((n, 2), dtype=bool)

    def fresh() -> FanucPmcSink:
        s = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode=mode, max_step_um=5, min_update_s=0.3))
        s.bind(["x1", "x2"], 1.0)
        s.open(float(t[0]) - 1.0)
        assert s.sync(float(t[0]) - 1.0)
        return s

    ref, got = fresh(), fresh()
    a1, c1, a2, c2 = (np.zeros((n, 2)) for _ in range(4))
    Sink.write_rows(ref, t, words, changed, corr, en, a1, c1)
    got.write_rows(t, words, changed, corr, en, a2, c2)
    np.testing.assert_array_equal(a2, a1)
    np.testing.assert_array_equal(c2, c1)
    assert (a1 != c1).any()  # the shift trails the word where 0.3 s per step binds
    ref.link.flush()  # both PMCs' scans run up to the sink's time
    got.link.flush()
    assert got.pmc.mem == ref.pmc.mem and got.sent_lsb == ref.sent_lsb and got.time.now_s == ref.time.now_s
    assert ref.pmc.alarms() == 0


def test_a_pmc_found_holding_another_shift_after_its_link_was_lost_is_stepped_from_there() -> None:
    """The PMC restarted while compd ran (a power cycle: it holds 0 again): when the link is back,
    the sink reads back what it applies and steps up from there, one max_step_um at a time, rather
    than believing its own last step is still applied (the machine left uncompensated)."""
    first = FanucPmc(step_limit_um=10)
    scan: PmcScanThread | None = PmcScanThread(first).start()
    srv = ModbusServerThread(first, port=0).start()
    port = srv.port
    second = _Spy(step_limit_um=10)
    scan2: PmcScanThread | None = None
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", host="127.0.0.1", port=port, max_step_um=5, min_update_s=0.02))
    sink.bind(["x1", "x2"], 1.0)
    sink.open(time.monotonic())
    try:
        assert sink.resync(5.0, time.monotonic())
        word = encode(25, -12)
        _run_until(sink, word, lambda: first.applied_um() == [25.0, -12.0])
        srv.stop()
        scan.stop()
        scan = None
        srv = ModbusServerThread(second, port=port).start()  # the same address, a PMC holding 0
        scan2 = PmcScanThread(second).start()
        _run_until(sink, word, lambda: second.applied_um() == [25.0, -12.0])
        assert sink.syncs == 2 and sink.held_um() == {"x1": 0.0, "x2": 0.0}
        assert max(abs(c[2]) for c in second.changes) <= 5.0 and second.alarms() == 0
    finally:
        sink.close()
        srv.stop()
        for s in (scan, scan2):
            if s is not None:
                s.stop()


def _run_until(sink: FanucPmcSink, word: int, done: Callable[[], bool], timeout_s: float = 30.0) -> None:
    """The daemon's cycle against a PMC on its own clock: sync, write, 2 ms apart, until `done`."""
    deadline = time.monotonic() + timeout_s
    first = True
    while not done():
        assert time.monotonic() < deadline, "timed out"
        now = time.monotonic()
        first = sink.sync(now) or first
        sink.write(word, Z, EN, first, now)
        first = False
        time.sleep(0.002)

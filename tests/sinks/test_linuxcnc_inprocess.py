"""linuxcnc sink on LinuxCNC's external offsets emulated in process (compd.plc.eoffsets): counts from what's applied."""

from __future__ import annotations

import numpy as np
import pytest

from compd.plc.eoffsets import Eoffsets, regs_s32, s32_regs
from compd.sinks.linuxcnc import LinuxcncConfig, LinuxcncSink


class _Model:
    def __init__(self, outputs):
        self.outputs = outputs


def _sink(device=None, outputs=("z",), **kw):
    sink = LinuxcncSink(LinuxcncConfig(kind="linuxcnc", in_process=True, **kw), device=device)
    sink.bind(list(outputs), 1.0)
    sink.bind_model(_Model(list(outputs)))
    sink.open(0.0)
    assert sink.sync(0.0)  # what LinuxCNC applies read back before anything is written
    return sink


def test_s32_registers_round_trip():
    for v in (0, 1, -1, 123456789, -(1 << 31), (1 << 31) - 1):
        assert regs_s32(*s32_regs(v)) == v


def test_the_offset_has_the_sign_and_size_of_the_correction():
    sink = _sink(count_um=0.1)
    out = np.zeros(1)
    sink.write(0, np.array([12.34]), np.array([True]), True, 0.01)
    sink.settle(0.01)
    sink.applied_um(out)
    assert out[0] == pytest.approx(12.3, abs=0.05 + 1e-9)
    sink.write(0, np.array([-7.0]), np.array([True]), True, 0.02)
    sink.settle(0.02)
    sink.applied_um(out)
    assert out[0] == pytest.approx(-7.0, abs=1e-6)
    sink.write(0, np.array([5.0]), np.array([False]), True, 0.03)  # disabled: the offset goes to 0
    sink.settle(0.03)
    sink.applied_um(out)
    assert out[0] == pytest.approx(0.0, abs=1e-6)


def test_a_restart_counts_from_what_linuxcnc_applies():
    """A device left at +8 µm by an earlier run with its counts at 5000 (another run's counts pin):
    the new sink holds 8 µm, and its correction of 10 µm moves the offset by 2 µm, not by 10 − 500."""
    dev = Eoffsets(1, 0.1)
    dev.counts, dev.enable, dev.register, dev.applied_um = [5000], [1], [80], [8.0]
    sink = _sink(device=dev, count_um=0.1)
    assert sink.held_um() == {"z": pytest.approx(8.0)}
    out = np.zeros(1)
    sink.applied_um(out)
    assert out[0] == pytest.approx(8.0)
    sink.write(0, np.array([10.0]), np.array([True]), True, 0.01)
    sink.settle(0.01)
    sink.applied_um(out)
    assert out[0] == pytest.approx(10.0, abs=1e-6)
    assert dev.counts == [5020]


def test_counts_turn_the_offset_on_without_moving_it():
    dev = Eoffsets(1, 0.1)
    dev.counts, dev.enable = [-300], [0]  # counts left on the pin, the offset disabled
    sink = _sink(device=dev)
    sink.settle(0.0)
    assert dev.enable == [1] and dev.applied_um == [0.0]
    sink.write(0, np.array([1.0]), np.array([True]), True, 0.01)
    sink.settle(0.01)
    assert dev.applied_um[0] == pytest.approx(1.0)


def test_safe_walks_the_offset_to_zero():
    sink = _sink(count_um=0.1, safe_ramp_um_per_s=50.0)
    sink.write(0, np.array([30.0]), np.array([True]), True, 0.01)
    sink.settle(0.01)
    assert sink.safe()
    assert sink.device.applied_um[0] == pytest.approx(0.0, abs=1e-9)


def test_two_axes_each_to_its_own_offset():
    sink = _sink(outputs=("x", "z"), axes=["x", "z"])
    out = np.zeros(2)
    sink.write(0, np.array([3.0, -4.0]), np.array([True, True]), True, 0.01)
    sink.settle(0.01)
    sink.applied_um(out)
    assert out == pytest.approx([3.0, -4.0])


def test_the_config_refuses_a_bad_component_name():
    with pytest.raises(ValueError, match="component"):
        LinuxcncConfig(kind="linuxcnc", in_process=True, component="1 bad")

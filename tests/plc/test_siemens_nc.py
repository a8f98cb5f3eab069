"""The NC software PLC's IPO cycles: an absolute schedule, the ramp at MD32760 the same run in one call or many."""

from __future__ import annotations

import numpy as np
import pytest

from compd.plc.siemens_nc import BLOCK, K0, SiemensNc, f32_regs


def test_the_ramp_is_the_same_run_in_one_call_or_cycle_by_cycle():
    """IPO cycle k is due at start + k·ipo_s; the applied ΔK after a run of cycles is the same
    whether the NC is advanced once or every few ms, float32 by float32 (and its counters)."""
    one, many = SiemensNc(2, ipo_s=0.004), SiemensNc(2, ipo_s=0.004)
    for nc in (one, many):
        nc.start_at(5.0)
        nc.write_registers(K0, f32_regs(0.012))
        nc.write_registers(BLOCK + K0, f32_regs(-0.003))
    t = 5.0
    for _ in range(800):
        t += 0.0031
        many.advance_to(t)
    one.advance_to(t)
    assert one.mem == many.mem and one.cycles == many.cycles == int((t - 5.0) / 0.004) + 1
    cap_mm = one.cap_mm(0)
    assert one.applied_mm()[0] == pytest.approx(0.012, abs=1e-7)  # 2.48 s at 5 µm/s: there
    assert np.isclose(cap_mm * 1000.0, 0.02)


def test_a_ramp_cut_short_by_the_time_moves_a_cap_per_cycle():
    nc = SiemensNc(1, ipo_s=0.004)
    nc.start_at(0.0)
    nc.write_registers(K0, f32_regs(0.1))
    nc.advance_to(0.4)  # cycles at 0, 0.004, ..., 0.4: 101
    assert nc.applied_mm()[0] == pytest.approx(101 * nc.cap_mm(0), rel=1e-5)
    assert not nc.settled()

"""Closed loop, lathe (paper 001): AR(1) through the Siemens NC over Modbus TCP, a shortened unseen day."""

from __future__ import annotations

import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

# The unseen day's first 5 plant-hours: 1 h stopped, then 1500 rpm jobs with pauses
# (the error reaches ~15 um). In lockstep; SPEEDUP only sets compd's period (4 s).
HOURS, SPEEDUP = 5.0, 7200.0
# C1 at standstill and at speed: measured 89 % on this stretch, 86 % over the whole day
REDUCTION_C1N_PCT = 82.0


def test_lathe_ar1_paper_form_closed_loop_cuts_the_error(tmp_path):
    """The paper's AR(1) with one C1 (`c1_by_speed=false`), through the Siemens NC."""
    ((tag, more),) = cl.MACHINES["lathe"].variants
    assert tag == "ar1_paper"
    model = cl.prepare_model("lathe", "ar1", tmp_path, more=more, tag=tag)
    r = cl.closed_loop("lathe", model, tmp_path, speedup=SPEEDUP, duration_s=HOURS * 3600, tag=tag)
    z = r["axes"]["z"]
    assert z["rms_before_um"] > 5.0  # the day heats the machine
    # measured 77-83 % on this stretch in real time, 86.2 % in lockstep (75.5 % over the
    # whole day, where the 1000 rpm jobs and the warmer shop come in: see the issue note)
    assert z["reduction_pct"] > 70.0, z
    assert z["max_abs_after_um"] < z["max_abs_before_um"]
    print(cl.table([r]))
    # no axis went to its fault policy; start-up no_data is logged and allowed (and
    # clock-jump events in a real-time run: a wall stall × the plant's speed-up)
    assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]
    assert r["sink"]["updates"] > 10  # corrections really went to the NC


def test_lathe_ar1_default_fit_keeps_c1_by_speed_closed_loop(tmp_path):
    """`compd fit --kind ar1` without options keeps compd's form (C1 at standstill and at speed)
    on the training day, where it predicts the later blocks better; same stretch and wiring."""
    model = cl.prepare_model("lathe", "ar1", tmp_path)
    assert "c1_table: []" not in model.read_text()  # the held-out comparison kept C1 by speed
    r = cl.closed_loop("lathe", model, tmp_path, speedup=SPEEDUP, duration_s=HOURS * 3600)
    print(cl.table([r]))
    z = r["axes"]["z"]
    assert z["rms_before_um"] > 5.0
    assert z["reduction_pct"] > REDUCTION_C1N_PCT, z
    assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]

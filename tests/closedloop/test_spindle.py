"""Closed loop, motorized spindle (paper 003): ξ-point axial and bearing-ring radial model through
the FANUC PMC's external shift over Modbus TCP, a shortened unseen day, against MLR on the same wiring."""

from __future__ import annotations

import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

# The unseen day's first 5 plant-hours: 9000 rpm jobs with pauses, coolant on (axial
# error up to ~17 um, the centrifugal lift included). In lockstep; SPEEDUP only sets
# compd's period (4 s); the two models run side by side.
HOURS, SPEEDUP = 5.0, 7200.0


def test_spindle_xi_model_through_the_pmc_cuts_the_axial_and_radial_error(tmp_path):
    kinds = ("xi_spindle", "mlr")
    runs = [
        dict(
            machine="spindle",
            model_file=cl.prepare_model("spindle", kind, tmp_path),
            workdir=tmp_path,
            speedup=SPEEDUP,
            duration_s=HOURS * 3600,
            tag=kind,
        )
        for kind in kinds
    ]
    rows = dict(zip(kinds, cl.closed_loops(runs), strict=True))
    print(cl.table(list(rows.values())))
    xi, mlr = rows["xi_spindle"]["axes"]["z"], rows["mlr"]["axes"]["z"]
    assert xi["rms_before_um"] > 5.0
    # measured 94.8 % on this stretch; one sensor at ξ tracks the rotor's mean temperature
    # and the speed gives the lift, so only the PMC's 1 um shift resolution and the slew remain
    assert xi["reduction_pct"] > 85.0, xi
    assert mlr["reduction_pct"] > 75.0, mlr
    # radial: the fitted ring gains (compd's form; RadialParams) leave ~0.1 um of model error
    # on the unseen day, so the word's whole-um steps and its 1 um no-chatter band (SPEC §2)
    # set what is left: 79.0 % on this stretch (2.0 um RMS before), as much as the true error
    # itself would reach through the same guard and encoder. The paper's unfitted u + c reads
    # the rings at their sensors' temperatures, under-reads the error by ~0.4 um while the
    # spindle turns, and reaches ~45 % here (the accept variant xi_spindle_paper).
    rad = rows["xi_spindle"]["axes"]["radial"]
    assert rad["rms_before_um"] > 1.5
    assert rad["reduction_pct"] > 72.0, rad
    for r in rows.values():
        assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]
        assert r["sink"]["updates"] > 5  # shift updates really went to the PMC

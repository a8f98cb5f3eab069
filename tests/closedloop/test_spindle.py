"""Closed loop, motorized spindle (paper 003): ξ-point axial and bearing-ring radial model through
the FANUC PMC's external shift over Modbus TCP, a shortened unseen day, against MLR on the same wiring."""

from __future__ import annotations

from rig import closedloop as cl

# The unseen day's first 5 plant-hours: 9000 rpm jobs with pauses, coolant on (axial
# error up to ~17 um, the centrifugal lift included). In lockstep; SPEEDUP only sets
# compd's period (4 s); the two models run side by side.
HOURS, SPEEDUP = 5.0, 7200.0


def test_spindle_xi_model_through_the_pmc_cuts_the_axial_and_radial_error(tmp_path):
    kinds = ("xi_spindle", "mlr")
    runs = [dict(machine="spindle", model_file=cl.prepare_model("spindle", kind, tmp_path), workdir=tmp_path,
                 speedup=SPEEDUP, duration_s=HOURS * 3600, tag=kind) for kind in kinds]
    rows = dict(zip(kinds, cl.closed_loops(runs), strict=True))
    print(cl.table(list(rows.values())))
    xi, mlr = rows["xi_spindle"]["axes"]["z"], rows["mlr"]["axes"]["z"]
    assert xi["rms_before_um"] > 5.0
    # measured ~94 % on this stretch; one sensor at ξ tracks the rotor's mean
    # temperature, so only the PMC's 1 um shift resolution and the slew remain
    assert xi["reduction_pct"] > 85.0, xi
    assert mlr["reduction_pct"] > 75.0, mlr
    # radial: measured ~45 % on this stretch (2.0 um RMS before, 1.1 after). The radial model
    # is the paper's u + c with nothing fitted: the centrifugal lift is axial (paper 003 §3.4).
    # Until issue 16 item 1 a k n² fitted on the radial residual reached ~75 % here by soaking
    # up ~0.5 um the rings model under-reads while the spindle turns (the plant's inner ring
    # follows the nose bearing's heat; the model reads it at T_xi). MLR, fitted on the radial
    # error, does better on this axis.
    rad = rows["xi_spindle"]["axes"]["radial"]
    assert rad["rms_before_um"] > 1.5
    assert rad["reduction_pct"] > 35.0, rad
    for r in rows.values():
        assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]
        assert r["sink"]["updates"] > 5  # shift updates really went to the PMC

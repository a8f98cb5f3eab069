"""Closed loop, gantry (paper 002): LVR through the PCI-1756 DO word into the PMC's X inputs
over Modbus TCP, a shortened unseen day, against MLR on the same wiring."""

from __future__ import annotations

import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

# The unseen day's first 5 plant-hours: 2 m/min over 100-700 mm with pauses (errors
# up to ~16 um on X2). In lockstep (closed_loop's default); SPEEDUP only sets compd's
# period (4 s, as the 7200x real-time run had); the two models run side by side.
HOURS, SPEEDUP = 5.0, 7200.0


def test_gantry_lvr_through_pci1756_and_pmc_cuts_both_axes(tmp_path):
    kinds = ("lvr", "mlr")
    runs = [
        dict(
            machine="gantry",
            model_file=cl.prepare_model("gantry", kind, tmp_path),
            workdir=tmp_path,
            speedup=SPEEDUP,
            duration_s=HOURS * 3600,
            tag=kind,
        )
        for kind in kinds
    ]
    rows = dict(zip(kinds, cl.closed_loops(runs), strict=True))
    print(cl.table(list(rows.values())))
    for axis in ("x1", "x2"):
        lvr = rows["lvr"]["axes"][axis]
        assert lvr["rms_before_um"] > 3.0
        # measured ~90 % (90.9/90.2 in lockstep); 75 % leaves room for the word's 1 um LSB
        assert lvr["reduction_pct"] > 75.0, (axis, lvr)
        assert rows["mlr"]["axes"][axis]["reduction_pct"] > 60.0
    for r in rows.values():
        assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]

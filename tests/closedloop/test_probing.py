"""Closed loop with probing (issue 17): the lathe's plant probes its Z axis through the Siemens NC's
probe-result block, compd's `probe` source reads it over Modbus TCP and the adapter takes the probes."""

from __future__ import annotations

import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

HOURS, SPEEDUP = 3.0, 7200.0  # in lockstep; SPEEDUP only sets compd's period (4 s)


def test_lathe_probes_reach_compd_and_an_outlier_is_rejected(tmp_path):
    model = cl.prepare_model("lathe", "ar1", tmp_path)
    probing = {"every_s": 900.0, "sigma_um": 0.3, "seed": 1, "outliers": [[5400.0, 30.0]]}
    r = cl.closed_loop(
        "lathe", model, tmp_path, speedup=SPEEDUP, duration_s=HOURS * 3600, tag="probing", probing=probing
    )
    print(cl.table([r]), r["adaptation"])
    z = r["adaptation"]["z"]
    # probes every 900 s from 900 s to before 10800 s: 11, the one at 5400 s with +30 um
    assert z["accepted"] >= 8, z
    assert z["rejected"] >= 1, z  # 30 um off: the innovation gate refuses it
    assert z["accepted"] + z["rejected"] <= 11
    assert z["last_probe_s"] is not None and z["last_probe_s"] > 9000
    assert abs(z["offset_um"]) < 5.0  # the model is good: the estimated offset stays small
    assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]
    assert r["axes"]["z"]["reduction_pct"] > 60.0, r["axes"]


def test_spindle_probes_through_the_fanuc_pmc_reach_both_axes(tmp_path):
    """The same through the PMC's D100–D107: the plant probes z and radial in turn."""
    model = cl.prepare_model("spindle", "xi_spindle", tmp_path)
    probing = {"every_s": 600.0, "sigma_um": 0.3, "seed": 2}
    r = cl.closed_loop(
        "spindle", model, tmp_path, speedup=SPEEDUP, duration_s=2 * 3600.0, tag="probing", probing=probing
    )
    print(cl.table([r]), r["adaptation"])
    ad = r["adaptation"]
    # 11 probes from 600 s to 6600 s, z and radial in turn: 6 and 5
    assert ad["z"]["accepted"] + ad["z"]["rejected"] == 6, ad
    assert ad["radial"]["accepted"] + ad["radial"]["rejected"] == 5, ad
    assert ad["z"]["accepted"] >= 5 and ad["radial"]["accepted"] >= 4, ad
    assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]

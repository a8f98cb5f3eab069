"""Closed loop, linear-motor feed axis (paper 000): the default fit reduced to K0 + tanβ (P − P0)
in the Siemens NC (position-dependent), a shortened unseen day.

On this plant's training day `compd fit --kind feed_axis` keeps compd's field form (the base
sensors along the stroke); it must leave less error than MLR on the same wiring. The paper's
analytic form reaches ~44 % over the whole day (its heat input does not know where the
coil works, and partial strokes heat one end): `make accept` runs it.
"""

from __future__ import annotations

import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

HOURS, SPEEDUP = 5.0, 7200.0
FIELD_MIN_PCT = 88.0  # measured 92.2 % on this stretch (MLR 80.5 %), 88.5 % over the whole day


def test_feed_axis_default_fit_beats_mlr_in_the_siemens_loop(tmp_path):
    kinds = ("feed_axis", "mlr")
    runs = [
        dict(
            machine="feed_axis",
            model_file=cl.prepare_model("feed_axis", kind, tmp_path),
            workdir=tmp_path,
            speedup=SPEEDUP,
            duration_s=HOURS * 3600,
            tag=kind,
        )
        for kind in kinds
    ]
    assert "field:" in runs[0]["model_file"].read_text() and "gain_integral" in runs[0]["model_file"].read_text()
    rows = dict(zip(kinds, cl.closed_loops(runs), strict=True))
    print(cl.table(list(rows.values())))
    field, mlr = rows["feed_axis"]["axes"]["y"], rows["mlr"]["axes"]["y"]
    assert rows["feed_axis"]["sink"]["updates"] > 5
    assert mlr["rms_before_um"] > 3.0
    assert field["reduction_pct"] > FIELD_MIN_PCT, field
    assert field["rms_after_um"] < mlr["rms_after_um"], (field, mlr)
    for r in rows.values():
        assert not any(k.startswith("fault") for k in r["faults"]), r["faults"]

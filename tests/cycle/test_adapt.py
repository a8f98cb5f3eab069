"""Probe adaptation (compd.cycle.adapt): the Kalman estimate converges, gates outliers, never touches
the prediction without probes, decays when stale, persists; replay applies a log's probes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from compd.core.config import AdaptConfig
from compd.core.probe import Probe
from compd.cycle.adapt import Adapter


def _run(adapter: Adapter, pred: float, t_s: float) -> float:
    out = np.zeros(1)
    adapter.apply(np.array([pred]), t_s, out)
    return float(out[0])


def test_without_probes_the_prediction_passes_unchanged():
    ad = Adapter(AdaptConfig(gain=True), ["z"])
    for k in range(100):
        p = 5.0 * math.sin(k / 10.0)
        assert _run(ad, p, k * 60.0) == p


def test_an_offset_is_learnt_within_two_probes_and_an_outlier_changes_nothing():
    rng = np.random.default_rng(1)
    ad = Adapter(AdaptConfig(), ["z"])
    true_offset = 3.0
    for k in range(2):  # two probes an hour apart; the model under-reads by 3 µm
        t = 3600.0 * (k + 1)
        ad.inbox.append(Probe(t, "z", 10.0 + true_offset + rng.normal(0, 0.3)))
        out = _run(ad, 10.0, t)
    assert abs(out - 13.0) < 0.6
    before = ad.get_state()
    ad.inbox.append(Probe(3 * 3600.0, "z", 10.0 + true_offset + 30.0))  # +30 µm: a chip on the artifact
    _run(ad, 10.0, 3 * 3600.0)
    after = ad.get_state()
    assert after["z"]["s"] == before["z"]["s"]
    assert [e["event"] for e in ad.events][-1] == "rejected"


def test_probes_rejected_in_a_row_raise_a_fault_event():
    ad = Adapter(AdaptConfig(reject_fault_after=3), ["z"])
    for k in range(4):
        ad.inbox.append(Probe(600.0 * k, "z", 100.0))
        _run(ad, 0.0, 600.0 * k)
    kinds = [e["event"] for e in ad.events]
    assert kinds.count("rejected") == 4 and kinds.count("fault") == 1 and ad.fault[0]
    ad.inbox.append(Probe(3000.0, "z", 0.1))  # a plausible probe again clears it
    _run(ad, 0.0, 3000.0)
    assert not ad.fault[0]


def test_a_gain_error_is_learnt():
    rng = np.random.default_rng(2)
    ad = Adapter(AdaptConfig(gain=True, initial_gain_sigma=0.5), ["x"])
    for k in range(12):
        p = 2.0 + 8.0 * (k % 3)  # probes at different predicted errors separate offset and gain
        ad.inbox.append(Probe(1800.0 * k, "x", 1.2 * p + rng.normal(0, 0.1)))
        _run(ad, p, 1800.0 * k)
    st = ad.get_status()["x"]
    assert st["gain"] == pytest.approx(0.2, abs=0.03)
    assert abs(st["offset_um"]) < 0.4


def test_observe_keeps_the_estimate_but_not_the_output():
    ad = Adapter(AdaptConfig(apply=False), ["z"])
    ad.inbox.append(Probe(0.0, "z", 4.0))
    assert _run(ad, 1.0, 0.0) == 1.0
    assert ad.get_status()["z"]["offset_um"] > 2.0 and ad.offset_um[0] > 2.0


def test_a_stale_estimate_decays_or_holds():
    for policy, expect in (("decay", math.exp(-2.0)), ("hold", 1.0)):
        ad = Adapter(
            AdaptConfig(
                apply_above_sigma=0.0,
                stale_after_s=3600.0,
                stale_policy=policy,
                decay_tau_s=1800.0,
                initial_offset_sigma_um=100.0,
            ),
            ["z"],
        )
        ad.inbox.append(Probe(0.0, "z", 5.0, sigma_um=0.01))
        b0 = _run(ad, 0.0, 0.0)
        _run(ad, 0.0, 3600.0)  # stale from here
        b1 = _run(ad, 0.0, 3600.0 + 3600.0)
        assert b0 == pytest.approx(5.0, abs=0.01)
        assert b1 == pytest.approx(b0 * expect, rel=1e-6)


def test_state_round_trips_and_a_reset_forgets():
    ad = Adapter(AdaptConfig(gain=True), ["x", "y"])
    ad.inbox.append(Probe(0.0, "y", 2.0))
    _run2 = np.zeros(2)
    ad.apply(np.array([0.0, 0.5]), 0.0, _run2)
    other = Adapter(AdaptConfig(gain=True), ["x", "y"])
    other.set_state(ad.get_state())
    assert other.get_status() == ad.get_status()
    other.reset()
    assert other.get_status()["y"]["offset_um"] == 0.0 and other.get_status()["y"]["accepted"] == 1


def test_config_bounds_are_one_line_errors():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="gate_sigma"):
        AdaptConfig(gate_sigma=0.5)
    with pytest.raises(ValidationError, match="stale_policy"):
        AdaptConfig(stale_policy="forget")


def test_a_residual_probe_adds_back_the_correction_applied_then():
    ad = Adapter(AdaptConfig(), ["z"])
    # the machine applies −9 µm against a predicted 9 µm; the probe sees +1 µm left over:
    # the whole error was 10 µm, so the model under-reads by 1 µm
    ad.inbox.append(Probe(0.0, "z", 1.0, sigma_um=0.01, residual=True))
    out = np.zeros(1)
    ad.apply(np.array([9.0]), 0.0, out, applied_um=np.array([-9.0]))
    assert out[0] == pytest.approx(10.0, abs=0.01)
    ad.inbox.append(Probe(1.0, "z", 1.0, residual=True))  # no applied correction known: not used
    ad.apply(np.array([9.0]), 1.0, out)
    assert ad.events[-1]["event"] == "no_correction_known"


def test_a_moving_axis_adds_back_the_correction_sent_where_it_measured():
    # the axis stood at 100 mm with −4 µm sent, then moved on to 500 mm (−9 µm) before the
    # CNC's result came: the probe measured at 100 mm, so −4 µm is what it saw in place
    ad = Adapter(AdaptConfig(slope_position={"y": "pos_y_mm"}), ["y"])
    ad.bind({"pos_y_mm": 0})
    out = np.zeros(1)
    for k, (y, sent) in enumerate([(100.0, -4.0), (100.0, -4.0), (300.0, -6.0), (500.0, -9.0)]):
        ad.read_positions(np.array([y]))
        ad.apply(np.array([-sent]), 0.002 * k, out)
        ad.record(np.array([-sent]), np.array([sent]))
    ad.inbox.append(Probe(0.008, "y", 0.5, sigma_um=0.01, position_mm=100.0, residual=True))
    ad.apply(np.array([9.0]), 0.008, out, applied_um=np.array([-9.0]))
    ev = ad.events[-1]
    assert ev["error_um"] == pytest.approx(4.5)  # 0.5 − (−4), not 0.5 − (−9)
    assert ev["innovation_um"] == pytest.approx(0.5)  # against the 4 µm predicted there
    # a position the axis was not at in the last seconds: the correction applied now
    ad.inbox.append(Probe(0.010, "y", 0.5, sigma_um=0.01, position_mm=250.0, residual=True))
    ad.apply(np.array([9.0]), 0.010, out, applied_um=np.array([-9.0]))
    assert ad.events[-1]["error_um"] == pytest.approx(9.5)


def test_a_slope_over_the_position_is_learnt_from_probes_at_several_positions():
    cfg = AdaptConfig(
        slope_position={"y": "pos_y_mm"}, slope_ref_mm=300.0, initial_offset_sigma_um=10.0, apply_above_sigma=0.0
    )  # the estimator alone: applied as estimated
    ad = Adapter(cfg, ["y"])
    ad.bind({"pos_y_mm": 0})
    rng = np.random.default_rng(3)
    out = np.zeros(1)
    for k in range(10):  # the model misses 1 µm + 4 µm/m × (y − 300 mm); probes at both ends
        y = 0.0 if k % 2 else 600.0
        miss = 1.0 + 4.0 * (y - 300.0) / 1000.0
        ad.inbox.append(Probe(600.0 * k, "y", 5.0 + miss + rng.normal(0, 0.05), position_mm=y))
        ad.read_positions(np.array([y]))
        ad.apply(np.array([5.0]), 600.0 * k, out)
    st = ad.get_status()["y"]
    assert st["slope_um_per_m"] == pytest.approx(4.0, abs=0.3) and st["offset_um"] == pytest.approx(1.0, abs=0.1)
    ad.read_positions(np.array([500.0]))  # between probes the correction follows the position
    ad.apply(np.array([5.0]), 6000.0, out)
    assert out[0] == pytest.approx(5.0 + 1.0 + 0.8, abs=0.15)


def test_slope_position_must_name_a_signal_and_an_axis():
    from compd.core.errors import BadInput

    with pytest.raises(BadInput, match="not a signal"):
        Adapter(AdaptConfig(slope_position={"y": "pos_q_mm"}), ["y"]).bind({"pos_y_mm": 0})
    with pytest.raises(BadInput, match="not an output"):
        Adapter(AdaptConfig(slope_position={"q": "pos_y_mm"}), ["y"]).bind({"pos_y_mm": 0})


def test_probes_never_hurt_a_model_that_is_right_and_correct_one_that_is_off():
    """The model's own error σ_m (its held-out RMSE) moves between probes; an estimate that does not
    stand out from its uncertainty stays off the prediction, a real offset comes through."""

    DAYS = 10  # noqa: N806 - enough days that one day's luck does not decide

    def run(offset_um: float, cfg: AdaptConfig) -> tuple[float, float]:
        rng = np.random.default_rng(7)  # the same days for every setting
        ad = Adapter(cfg, ["z"], model_sigma_um={"z": 1.0})
        sq_with = sq_without = 0.0
        out = np.zeros(1)
        wander = 0.0
        for k in range(DAYS * 24 * 60):  # minutes; the model's own error wanders by ~1 µm
            t = 60.0 * k
            wander = 0.98 * wander + rng.normal(0.0, 0.2)
            truth = 10.0 + offset_um + wander  # the machine's error; the model predicts 10
            if k % 120 == 60:  # a probe every 2 h, σ 0.3 µm
                ad.inbox.append(Probe(t, "z", truth + rng.normal(0.0, 0.3)))
            ad.apply(np.array([10.0]), t, out)
            sq_with += (truth - out[0]) ** 2
            sq_without += (truth - 10.0) ** 2
        return math.sqrt(sq_with / (DAYS * 1440)), math.sqrt(sq_without / (DAYS * 1440))

    right = run(0.0, AdaptConfig())
    assert right[0] <= right[1] * 1.02  # no offset: the probes change (almost) nothing
    naive = run(0.0, AdaptConfig(apply_above_sigma=0.0, model_sigma_um=0.0))
    assert naive[0] > right[0]  # taking each probe at its word chases the model's own error
    off = run(4.0, AdaptConfig())
    assert off[0] < 0.5 * off[1]  # a real 4 µm offset is corrected


def test_the_model_sigma_comes_from_the_fit_unless_configured():
    assert Adapter(AdaptConfig(), ["z"], model_sigma_um={"z": 0.8}).model_sigma_um == [0.8]
    assert Adapter(AdaptConfig(model_sigma_um=0.2), ["z"], model_sigma_um={"z": 0.8}).model_sigma_um == [0.2]
    assert Adapter(AdaptConfig(), ["z"]).model_sigma_um == [0.0]


def test_a_probe_on_a_model_at_p0_is_compared_with_its_slope_where_it_measured():
    """A model whose output is the error at P0 and whose slope the CNC applies (Siemens tanβ): a
    probe at y = P0 + 200 mm measures K0 + slope·200 mm; compared with K0 alone it would teach a
    false offset of the slope's share."""
    ad = Adapter(AdaptConfig(apply_above_sigma=0.0), ["y"])
    out = np.zeros(1)
    # K0 = 4 µm at P0 = 300 mm, slope 0.01 µm/mm: the error at 500 mm is 6 µm, and the probe reads it
    ad.inbox.append(Probe(0.0, "y", 6.0, sigma_um=0.05, position_mm=500.0))
    ad.apply(np.array([4.0]), 0.0, out, terms=[(0.01, 300.0)])
    assert ad.events[-1]["innovation_um"] == pytest.approx(0.0, abs=1e-9)
    assert out[0] == pytest.approx(4.0, abs=1e-6)  # no offset learnt: the model was right there


def test_the_offset_starts_within_the_models_own_error():
    """Before the first probe a fitted model is off by about its own error σ_m, not by an arbitrary
    5 µm: one probe that shows a momentary miss moves it only as far as that prior allows."""
    assert Adapter(AdaptConfig(), ["z"], model_sigma_um={"z": 0.8}).est[0].P[0, 0] == pytest.approx(0.64)
    assert Adapter(AdaptConfig(), ["z"]).est[0].P[0, 0] == pytest.approx(25.0)  # σ_m unknown
    assert Adapter(AdaptConfig(initial_offset_sigma_um=2.0), ["z"], model_sigma_um={"z": 0.8}).est[0].P[
        0, 0
    ] == pytest.approx(4.0)
    out = np.zeros(1)
    wide = Adapter(AdaptConfig(initial_offset_sigma_um=5.0), ["z"], model_sigma_um={"z": 0.8})
    tight = Adapter(AdaptConfig(), ["z"], model_sigma_um={"z": 0.8})
    for ad in (wide, tight):
        ad.inbox.append(Probe(0.0, "z", 12.0))  # the model says 10; one probe sees 2 µm more
        ad.apply(np.array([10.0]), 0.0, out)
    assert tight.est[0].s[0] < 0.5 * wide.est[0].s[0]


def test_a_probe_with_numbers_no_probe_measures_is_rejected_with_its_reason():
    """What a device or a replayed log hands over is checked where every probe passes: a σ or
    an error that is not finite or beyond the bounds is rejected, named, and changes nothing."""
    nan, inf = math.nan, math.inf
    cases = [
        ({"error_um": 1.0, "sigma_um": nan}, "sigma_um"),
        ({"error_um": 1.0, "sigma_um": inf}, "sigma_um"),
        ({"error_um": 1.0, "sigma_um": 1e200}, "sigma_um"),
        ({"error_um": 1.0, "sigma_um": 1e-9}, "sigma_um"),
        ({"error_um": nan}, "error_um"),
        ({"error_um": -inf}, "error_um"),
        ({"error_um": 2e6}, "error_um"),  # 2 m: an int32 of nm in the CNC's block holds it
        ({"error_um": 1.0, "position_mm": inf}, "position_mm"),
        ({"error_um": 1.0, "position_mm": 1e300}, "position_mm"),
    ]
    ad = Adapter(AdaptConfig(reject_fault_after=100), ["z"])
    out = np.zeros(1)
    before = ad.get_state()
    for k, (numbers, key) in enumerate(cases):
        ad.inbox.append(Probe(float(k), "z", source="cnc_probe", residual=True, **numbers))
        ad.apply(np.array([5.0]), float(k), out, applied_um=np.array([-5.0]))
        ev = ad.events[-1]
        assert ev["event"] == "rejected" and ev["reason"].startswith(key), (numbers, ev)
        assert ev["source"] == "cnc_probe"
    after = ad.get_state()["z"]
    assert after["s"] == before["z"]["s"] and after["accepted"] == 0 and after["rejected"] == len(cases)
    assert all(math.isfinite(v) for row in after["P"] for v in row)
    assert math.isnan(ad.probe_um[0])  # none of them is a measurement for the data log or the shadow's score
    ad.inbox.append(Probe(100.0, "z", 0.2, sigma_um=1000.0))  # the bounds themselves are taken
    ad.apply(np.array([0.0]), 100.0, out)
    assert ad.events[-1]["event"] == "accepted" and "reason" not in ad.events[-1]


def test_an_update_that_would_go_non_finite_is_rejected_and_the_estimate_kept():
    """σ² overflowing (a σ of 1e200, as the socket once took it) or a position far off a slope
    axis would make s or P NaN; the filter rejects the probe instead and keeps what it had."""
    ad = Adapter(AdaptConfig(slope_position={"y": "pos_y_mm"}), ["y"])
    e = ad.est[0]
    s0, P0 = e.s.copy(), e.P.copy()
    for sigma_um, pos_m in ((1e200, 0.0), (0.3, 1e200)):
        ok, _nu, _sd, why = e.update(5.0, 6.0, sigma_um, 10.0, pos_m)
        assert not ok and why, (sigma_um, pos_m)
        assert np.array_equal(e.s, s0) and np.array_equal(e.P, P0)
    assert e.rejected == 2 and e.accepted == 0
    ok, _nu, _sd, why = e.update(5.0, 6.0, 0.3, 10.0, 0.1)  # a sane probe is still taken
    assert ok and why is None and np.isfinite(e.P).all()


def test_a_saved_state_that_is_not_finite_or_not_a_covariance_is_refused_whole():
    ad = Adapter(AdaptConfig(), ["x", "z"])
    good = {"s": [1.5], "P": [[0.04]], "t_probe_s": 3.0, "accepted": 2, "rejected": 0, "probe_age_s": 10.0}
    for bad, named in (
        ({"P": [[math.nan]]}, "P[0]"),
        ({"s": [math.inf]}, "s holds"),
        ({"P": [[-1.0]]}, "positive semi-definite"),
        ({"probe_age_s": math.nan}, "probe_age_s"),
        ({"accepted": 1e400}, "accepted"),
    ):
        with pytest.raises(ValueError, match=r"^z: .*" + named.replace("[", r"\[")):
            ad.set_state({"x": good, "z": {**good, **bad}})
        assert ad.get_status()["x"]["accepted"] == 0  # nothing of it taken, not even the good axis
    g = Adapter(AdaptConfig(gain=True), ["z"])
    with pytest.raises(ValueError, match="not symmetric"):
        g.set_state({"z": {**good, "s": [0.0, 0.0], "P": [[1.0, 0.5], [0.0, 1.0]]}})
    with pytest.raises(ValueError, match="s has 1 terms"):
        g.set_state({"z": good})
    ad.set_state({"x": good, "z": good})
    assert ad.get_status()["z"]["offset_um"] == 1.5 and ad.get_status()["x"]["accepted"] == 2

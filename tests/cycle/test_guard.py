"""The guard: clamp, slew, plausibility, fault policies, recovery without steps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from compd.core.config import GuardConfig, SignalLimits
from compd.core.frame import Frame, Quality
from compd.cycle.guard import Guard


def run(guard: Guard, frame: Frame, preds, dt=0.1, t0=0.0, bad_from=None, bad_to=None):  # noqa: ANN001
    outs, ens = [], []
    t = t0
    for k, p in enumerate(preds):
        frame.set(0, 25.0, Quality.GOOD, t)
        if bad_from is not None and bad_from <= k < bad_to:
            frame.quality[0] = Quality.BURNOUT
        ok = guard.check_inputs(frame, t)
        guard.update(np.array([p]), ok, t)
        outs.append(guard.out_um[0])
        ens.append(bool(guard.enable[0]))
        t += dt
    return np.array(outs), ens


def make(policy: str = "hold", **kw) -> tuple[Guard, Frame]:  # noqa: ANN003
    frame = Frame(["T"])
    cfg = GuardConfig(fault_policy=policy, max_slew_um_per_s=10.0, recovery_s=1.0, **kw)
    return Guard(cfg, ["z"], frame, ["T"]), frame


def test_slew_and_clamp() -> None:
    g, f = make(max_abs_um=20.0)
    out, _ = run(g, f, [100.0] * 40)
    steps = np.abs(np.diff(np.concatenate([[0.0], out])))
    assert steps.max() <= 1.0 + 1e-12  # 10 µm/s × 0.1 s
    assert out[-1] == pytest.approx(-20.0)  # correction = −prediction, clamped


def test_a_prediction_beyond_the_clamp_is_flagged_and_said_once() -> None:
    """An axis whose model asks for more than max_abs_um is `clamped` (the status says saturated)
    with one `clamped` event naming the prediction, and `unclamped` when it comes back inside."""
    g, f = make(max_abs_um=20.0)
    run(g, f, [5.0] * 5 + [455400.0] * 30 + [10.0] * 5)
    said = [(subject, event) for _, subject, event, _ in g.events]
    assert said.count(("z", "clamped")) == 1 and said.count(("z", "unclamped")) == 1
    why = next(r for _, _, e, r in g.events if e == "clamped")
    assert why == "the model predicts 455400.0 um, beyond the clamp of 20 um"
    assert not g.clamped[0] and g.state[0] == 1  # inside again, still normal
    run(g, f, [-30.0] * 3, t0=10.0)
    assert g.clamped[0] and g.target_um[0] == pytest.approx(20.0)


@pytest.mark.parametrize("policy", ["hold", "ramp_to_zero", "disable"])
def test_fault_policies_and_recovery(policy: str) -> None:
    g, f = make(policy, ramp_um_per_s=2.0)
    out, en = run(g, f, [10.0] * 200, bad_from=60, bad_to=100)
    held = out[59]
    assert held == pytest.approx(-10.0)
    if policy == "hold":
        assert np.allclose(out[60:100], held)
        assert all(en[60:100])
    elif policy == "ramp_to_zero":
        assert np.all(np.abs(np.diff(out[59:100])) <= 0.2 + 1e-12)
        assert out[99] == pytest.approx(held + 2.0 * 4.0, abs=0.21)
    else:
        assert not any(en[60:100])
        assert np.allclose(out[60:100], 0.0)
    # recovery waits recovery_s (1 s = 10 cycles) of good input, then slews, never steps
    steps = np.abs(np.diff(out[99:]))
    assert steps.max() <= 1.0 + 1e-12
    assert out[-1] == pytest.approx(-10.0)
    assert g.get_status()["z"]["state"] == "normal"
    assert g.faults.get("bad:burnout") == 1


def test_nan_prediction_is_a_fault() -> None:
    g, f = make("hold")
    out, _ = run(g, f, [5.0] * 20 + [math.nan] * 5)
    assert np.isfinite(out).all()
    assert out[-1] == out[19]


def test_plausibility_range_rate_stale() -> None:
    frame = Frame(["T"])
    cfg = GuardConfig(
        signals={"T": SignalLimits(min=0, max=50, max_rate_per_s=1.0, rate_allowance=0.2, stale_after_s=2.0)}
    )
    g = Guard(cfg, ["z"], frame, ["T"])
    frame.set(0, 25.0, Quality.GOOD, 0.0)
    assert g.check_inputs(frame, 0.0)
    frame.set(0, 60.0, Quality.GOOD, 1.0)
    assert not g.check_inputs(frame, 1.0) and frame.quality[0] == Quality.OUT_OF_RANGE
    frame.set(0, 30.0, Quality.GOOD, 2.0)  # +5 °C in 2 s: implausible rate
    assert not g.check_inputs(frame, 2.0) and frame.quality[0] == Quality.IMPLAUSIBLE
    frame.set(0, 25.5, Quality.GOOD, 3.0)
    assert g.check_inputs(frame, 3.0)
    assert not g.check_inputs(frame, 6.0) and frame.quality[0] == Quality.STALE


def test_frozen_sensor_is_flagged_only_while_the_others_move() -> None:
    frame = Frame(["A", "B"])
    limits = {"A": SignalLimits(frozen_after_s=2.0, frozen_band=0.05)}
    g = Guard(GuardConfig(signals=limits), ["z"], frame, ["A", "B"])
    t, quality = 0.0, []
    for k in range(100):  # 10 s at 0.1 s: A stuck from 3 s on; B moves until 6 s, then stops too
        a = 20.0 + 0.1 * min(k, 30)
        b = 20.0 + 0.1 * min(k, 60)
        frame.set(0, a, Quality.GOOD, t)
        frame.set(1, b, Quality.GOOD, t)
        g.check_inputs(frame, t)
        quality.append(int(frame.quality[0]))
        t += 0.1
    frozen = [k for k, q in enumerate(quality) if q == Quality.FROZEN]
    # frozen once A has not moved for 2 s (from k≈51) while B still moved in that window;
    # good again once B stopped too (a whole machine at rest is not a stuck sensor)
    assert frozen and frozen[0] == 51 and 60 <= frozen[-1] <= 81
    assert quality[-1] == Quality.GOOD
    assert ("A", "bad", "frozen") in [(s, e, r) for _, s, e, r in g.events]


def test_a_single_input_freezes_on_time_alone() -> None:
    frame = Frame(["T"])
    g = Guard(GuardConfig(signals={"T": SignalLimits(frozen_after_s=1.0)}), ["z"], frame, ["T"])
    for k in range(30):
        frame.set(0, 25.0, Quality.GOOD, k * 0.1)
        ok = g.check_inputs(frame, k * 0.1)
    assert not ok and frame.quality[0] == Quality.FROZEN


def test_clock_jump_never_licenses_a_step() -> None:
    g, f = make()
    run(g, f, [0.0] * 5)
    f.set(0, 25.0, Quality.GOOD, 3600.0)
    g.clock_jump(3600.0, 0.1)  # the loop saw it woke an hour late
    ok = g.check_inputs(f, 3600.0)
    g.update(np.array([50.0]), ok, 3600.0)
    assert abs(g.out_um[0]) <= 10.0 * 0.1 + 1e-12
    assert any(e == "jump" for _, _, e, _ in g.events)


def test_an_input_without_a_rate_limit_beside_one_with_raises_no_warning() -> None:
    """The demo's T_xi has max_rate_per_s, its speed_rpm has none: the same sample read again
    (dt 0) must not make inf × 0 (a numpy warning every cycle); a real jump is still caught."""
    import warnings

    frame = Frame(["T", "n"])
    cfg = GuardConfig(signals={"T": SignalLimits(max_rate_per_s=2.0), "n": SignalLimits(min=0.0, max=30000.0)})
    g = Guard(cfg, ["z"], frame, ["T", "n"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for t, temp, speed in ((0.0, 25.0, 0.0), (0.1, 25.0, 0.0), (0.2, 25.0, 12000.0), (0.3, 25.0, 12000.0)):
            for i, v in enumerate((temp, speed)):
                frame.set(i, v, Quality.GOOD, 0.0 if t < 0.2 else 0.2)  # stamps repeat: no new sample
            assert g.check_inputs(frame, t)
        frame.set(0, 40.0, Quality.GOOD, 0.3)  # +15 °C in 0.1 s: implausible
        assert not g.check_inputs(frame, 0.4)


@pytest.mark.parametrize("policy", ["hold", "ramp_to_zero", "disable"])
def test_update_rows_equals_update_row_by_row(policy: str) -> None:
    """The replay's `update_rows` gives what `update` gives row by row, whatever comes: NaN
    predictions, bad and degraded rows, holds, clamps, time that repeats or runs backwards."""
    rng = np.random.default_rng({"hold": 1, "ramp_to_zero": 2, "disable": 3}[policy])
    n = 3000
    t = np.cumsum(rng.choice([0.0, 0.002, 0.5, 1.0, 10.0, 60.0], n, p=[0.02, 0.1, 0.3, 0.4, 0.15, 0.03]))
    t[rng.integers(0, n, 10)] -= 5.0  # a clock that goes back now and then
    pred = np.cumsum(rng.normal(0.0, 2.0, (n, 2)), axis=0)
    pred[rng.random((n, 2)) < 0.01] = np.nan
    ok = rng.random(n) > 0.02
    ok[1500:1600] = False
    degraded = np.zeros(n, dtype=bool)
    degraded[2000:2100] = True
    hold = np.zeros((n, 2), dtype=np.uint8)
    hold[700:900, 0] = 1
    hold[2500:2600, 1] = 2

    def fresh() -> Guard:
        frame = Frame(["T"])
        cfg = GuardConfig(
            fault_policy=policy, max_slew_um_per_s=3.0, max_abs_um=50.0, recovery_s=20.0, ramp_um_per_s=1.0
        )
        return Guard(cfg, ["x1", "x2"], frame, ["T"])

    ref = fresh()
    out, en, st, dts = np.zeros((n, 2)), np.zeros((n, 2), bool), np.zeros((n, 2), np.uint8), np.zeros(n)
    for i in range(n):
        ref.hold[:] = hold[i]
        ref.update(pred[i], bool(ok[i]), float(t[i]), degraded=bool(degraded[i]))
        out[i], en[i], st[i], dts[i] = ref.out_um, ref.enable, ref.state, ref.dt_s
    got = fresh()
    out2, en2, st2, dts2 = np.zeros((n, 2)), np.zeros((n, 2), bool), np.zeros((n, 2), np.uint8), np.zeros(n)
    got.update_rows(pred, ok, t, degraded, hold, out2, en2, st2, dts2)
    np.testing.assert_array_equal(out2, out)
    np.testing.assert_array_equal(en2, en)
    np.testing.assert_array_equal(st2, st)
    np.testing.assert_array_equal(dts2, dts)
    assert got.faults == ref.faults and got.events == ref.events
    assert ref.faults.get("clamped", 0) > 0  # the walk reaches the clamp: both paths flag it alike
    for name in ("out_um", "enable", "target_um", "state", "hold", "clamped"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    assert (got._last_t, got.dt_s, got.degraded) == (ref._last_t, ref.dt_s, ref.degraded)
    assert (st == 1).mean() > 0.5  # mostly the float path's NORMAL rows


def test_plain_rows_pass_check_inputs_after_rows_that_passed() -> None:
    """A row `plain_rows` marks, after a row that passed every check, passes them too (and
    leaves the guard as `passed` says); the rows it does not mark are those that can fail."""
    rng = np.random.default_rng(7)
    n = 400
    t = np.cumsum(rng.choice([0.0, 1.0, 2.0], n, p=[0.03, 0.8, 0.17]))
    X = 20.0 + np.cumsum(rng.normal(0.0, 0.2, (n, 2)), axis=0)
    X[rng.random((n, 2)) < 0.02] = np.nan
    X[50, 1] = 95.0  # out of range
    X[80, 0] += 10.0  # too fast
    frame = Frame(["A", "B"])
    cfg = GuardConfig(signals={"A": SignalLimits(max_rate_per_s=1.0), "B": SignalLimits(min=0.0, max=80.0)})
    g = Guard(cfg, ["z"], frame, ["A", "B"])
    plain = g.plain_rows(X, t)
    assert not plain[50] and not plain[80] and not plain[81] and plain.sum() > n // 2
    last_ok = False
    for i in range(n):
        frame.values[:] = X[i]
        frame.quality[:] = np.where(np.isnan(X[i]), Quality.NO_DATA, Quality.GOOD)
        frame.stamp_s[:] = t[i]
        ok = g.check_inputs(frame, float(t[i]))
        if plain[i] and last_ok:
            assert ok, i
        last_ok = ok
    shadow = Guard(cfg, ["z"], Frame(["A", "B"]), ["A", "B"])
    shadow.passed(X[-1], float(t[-1]))
    if last_ok:
        np.testing.assert_array_equal(shadow._prev_val, g._prev_val)
        np.testing.assert_array_equal(shadow._prev_t, g._prev_t)


def test_a_start_goes_on_from_what_the_machine_applies() -> None:
    """Seeded with the machine's correction (the sink read it back), the guard never steps: before
    the model's first prediction it takes it to 0 at the ramp (enabled while not 0), and from the
    first prediction it slews from wherever it stands."""
    g, f = make(ramp_um_per_s=2.0)
    g.seed(0, -9.0, 0.0)
    assert g.out_um[0] == -9.0 and g.enable[0]
    assert [e for _, _, e, _ in g.events] == ["synced"]
    out, ens = run(g, f, [math.nan] * 10)  # no prediction yet: 2 µm/s × 0.1 s a cycle toward 0
    np.testing.assert_allclose(out, -9.0 + 0.2 * np.arange(10))
    assert all(ens) and g.state[0] == 0  # still starting
    out, ens = run(g, f, [5.0] * 40, t0=1.0)  # the model starts: slews from −7.2 to −5 at 10 µm/s
    steps = np.abs(np.diff(np.concatenate([[-7.2], out])))
    assert steps.max() <= 1.0 + 1e-9 and out[-1] == pytest.approx(-5.0) and all(ens)


def test_a_start_with_nothing_to_predict_ends_at_zero_disabled() -> None:
    g, f = make(ramp_um_per_s=5.0)
    g.seed(0, 3.0, 0.0)
    out, ens = run(g, f, [math.nan] * 20)
    assert out[-1] == 0.0 and not ens[-1] and np.abs(np.diff(out)).max() <= 0.5 + 1e-9

"""The one output limiter: the guard's cycle, the replay's float path and each contribution give its numbers.

Policy names round-trip.
"""

from __future__ import annotations

import math
from typing import Any, get_args

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from compd.core.config import ContributionParams, ContributionSetParams, FaultPolicy, GuardConfig
from compd.core.frame import Frame
from compd.cycle.contributions import Contributions
from compd.cycle.guard import Guard
from compd.cycle.limiter import (
    NORMAL,
    POLICY_NAMES,
    STATE_NAMES,
    TO_NORMAL,
    AxisState,
    Limiter,
    Policy,
)
from compd.cycle.statusblock import AXIS, PART

POLICY_LABELS = [p.label for p in Policy]
times = st.sampled_from([0.0, 0.002, 0.1, 0.5, 1.0, 3.0, 60.0, -1.0])  # a step's advance (−1: the clock went back)
wants = st.one_of(st.floats(-300.0, 300.0), st.just(math.nan), st.just(math.inf))
limits = st.fixed_dictionaries(
    {
        "max_abs_um": st.floats(0.5, 100.0),
        "max_slew_um_per_s": st.floats(0.01, 50.0),
        "fault_policy": st.sampled_from(POLICY_LABELS),
    }
)


@st.composite
def runs(draw: Any) -> dict[str, Any]:
    """Two axes, each with its clamp, slew and policy; per step a time advance, each axis's want
    (NaN, inf: lost), the inputs' verdict and the machine's hold. The limits and how often each
    thing happens are drawn; the steps come from a drawn seed (drawing each is slow)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.integers(1, 300))
    lost, bad, held = (draw(st.sampled_from([0.0, 0.02, 0.2, 0.6])) for _ in range(3))
    want = rng.normal(0.0, draw(st.sampled_from([1.0, 30.0, 300.0])), (n, 2))
    if draw(st.booleans()):
        want = np.cumsum(want, axis=0) / 5.0  # a walk, as a thermal error drifts
    want[rng.random((n, 2)) < lost] = np.nan
    want[rng.random((n, 2)) < lost / 10] = np.inf
    return {
        "axes": [draw(limits), draw(limits)],
        "ramp_um_per_s": draw(st.floats(0.01, 50.0)),
        "recovery_s": draw(st.sampled_from([0.0, 0.5, 2.0, 30.0])),
        "dt": rng.choice(
            [0.0, 0.002, 0.1, 0.5, 1.0, 3.0, 60.0, -1.0],
            n,  # −1: the clock went back
            p=[0.03, 0.1, 0.3, 0.2, 0.2, 0.1, 0.05, 0.02],
        ).tolist(),
        "want": want.tolist(),
        "ok": (rng.random(n) >= bad).tolist(),
        "hold": np.where(rng.random((n, 2)) < held, [1, 2], 0).tolist(),
    }


def _guard(run: dict[str, Any]) -> Guard:
    cfg = GuardConfig(
        ramp_um_per_s=run["ramp_um_per_s"],
        recovery_s=run["recovery_s"],
        axes={a: run["axes"][i] for i, a in enumerate(("x", "z"))},
    )
    return Guard(cfg, ["x", "z"], Frame(["T"]), ["T"])


@settings(max_examples=200, deadline=None)
@given(runs())
def test_the_guards_cycle_its_replay_path_and_the_limiter_alone_agree(run: dict[str, Any]) -> None:
    """Whatever comes (wants lost, clamps, holds, time that stands or runs back), the guard's cycle
    (`update`), the replay's rows (`update_rows`: its float path where every axis is normal) and a
    Limiter stepped alone give the same outputs, bit for bit."""
    n = len(run["dt"])
    t = np.cumsum(run["dt"])
    pred = -np.array(run["want"])  # the guard wants −prediction
    ok = np.array(run["ok"])
    hold = np.array(run["hold"], dtype=np.uint8)
    ref = _guard(run)
    lim = Limiter(
        [a["max_abs_um"] for a in run["axes"]],
        [a["max_slew_um_per_s"] for a in run["axes"]],
        [Policy.named(a["fault_policy"]) for a in run["axes"]],
        run["ramp_um_per_s"],
        run["recovery_s"],
    )
    out, en, stt, dts = np.zeros((n, 2)), np.zeros((n, 2), bool), np.zeros((n, 2), np.uint8), np.zeros(n)
    names = ("out_um", "enable", "state", "target_um", "clamped")
    seen = {name: np.zeros((n, 2)) for name in names}  # the guard's after each cycle, and the limiter's
    alone = {name: np.zeros((n, 2)) for name in names}
    dt_alone = np.zeros(n)
    last = math.nan
    for i in range(n):
        ref.hold[:] = hold[i]
        ref.update(pred[i], bool(ok[i]), float(t[i]))
        out[i], en[i], stt[i], dts[i] = ref.out_um, ref.enable, ref.state, ref.dt_s
        dt_alone[i] = dt = max(float(t[i]) - last, 0.0) if last == last else 0.0
        last = float(t[i])
        for k in range(2):
            if hold[i, k]:
                lim.held_off(k, dt)
            else:
                lim.step(k, run["want"][i][k] if ok[i] else math.nan, dt, float(t[i]))
        for name, mine in zip(names, (lim.value_um, lim.enable, lim.state, lim.target_um, lim.clamped), strict=True):
            seen[name][i] = getattr(ref, name)
            alone[name][i] = mine
    np.testing.assert_array_equal(dts, dt_alone)
    for name in names:
        np.testing.assert_array_equal(alone[name], seen[name], err_msg=name)
    got = _guard(run)
    out2, en2, st2, dts2 = np.zeros((n, 2)), np.zeros((n, 2), bool), np.zeros((n, 2), np.uint8), np.zeros(n)
    got.update_rows(pred, ok, t, np.zeros(n, dtype=bool), hold, out2, en2, st2, dts2)
    np.testing.assert_array_equal(out2, out)
    np.testing.assert_array_equal(en2, en)
    np.testing.assert_array_equal(st2, stt)
    np.testing.assert_array_equal(dts2, dts)
    assert got.events == ref.events and got.faults == ref.faults
    for name in ("out_um", "enable", "target_um", "state", "clamped"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)


def _sum(limit: dict[str, Any], ramp: float, recovery: float) -> Contributions:
    """A sum of one contribution whose model predicts its input itself (mlr: 1 µm per K from 0 °C)."""
    part = ContributionParams(
        name="col",
        kind="mlr",
        inputs=["T"],
        outputs=["z"],
        params={"coef_um_per_k": [[1.0]], "intercept_um": [0.0], "t0_c": [0.0]},
        max_abs_um=[limit["max_abs_um"]],
        max_slew_um_per_s=[limit["max_slew_um_per_s"]],
        fault_policy=[limit["fault_policy"]],
    )
    return Contributions(
        ContributionSetParams(contributions=[part], ramp_um_per_s=ramp, recovery_s=recovery), ["T"], ["z"]
    )


@settings(max_examples=300, deadline=None)
@given(
    limits,
    st.floats(0.01, 50.0),
    st.sampled_from([0.0, 0.5, 2.0, 30.0]),
    st.lists(st.tuples(times, wants), min_size=1, max_size=80),
)
def test_a_contributions_limit_is_the_guards(
    limit: dict[str, Any], ramp: float, recovery: float, steps: list[tuple[float, float]]
) -> None:
    """A contribution on its axis and a guard's axis with the same clamp, slew, policy, ramp and
    recovery, fed the same prediction, give the same value, state, clamp flag and events (a
    contribution under `disable` hands its axis NaN where the guard's axis is disabled)."""
    c = _sum(limit, ramp, recovery)
    said: list[tuple[float, str, str]] = []
    c.emit = lambda t, subject, event, reason: said.append((t, subject, event))
    g = Guard(GuardConfig(ramp_um_per_s=ramp, recovery_s=recovery, axes={"z": limit}), ["z"], Frame(["T"]), ["T"])
    lim = Limiter(
        [limit["max_abs_um"]], [limit["max_slew_um_per_s"]], [Policy.named(limit["fault_policy"])], ramp, recovery
    )
    out, pred = np.zeros(1), np.zeros(1)
    t, last = 0.0, math.nan
    for adv, x in steps:
        t += adv
        good = np.array([x == x and abs(x) != math.inf])
        c.run_degraded(np.array([x]), good, t, out)
        raw = float(c.part_raw_um[0])
        assert raw == x or not good[0]
        pred[0] = -raw
        g.update(pred, True, t)
        dt = max(t - last, 0.0) if last == last else 0.0
        last = t
        lim.step(0, raw, dt, t)
        assert c.part_state[0] == g.state[0] == lim.state[0]
        assert c.part_clamped[0] == g.clamped[0] == lim.clamped[0]
        assert g.out_um[0] == lim.value_um[0] and g.enable[0] == lim.enable[0]
        if limit["fault_policy"] == "disable" and g.state[0] != NORMAL:
            assert math.isnan(out[0]) and not g.enable[0] and g.out_um[0] == 0.0
        else:
            assert out[0] == c.part_um[0] == g.out_um[0]
    assert [e for _, _, e in said] == [e for _, _, e, _ in g.events]


def test_a_contribution_that_faults_while_recovering_says_so_and_a_lost_input_ends_its_clamp() -> None:
    """As an axis of the guard does: `fault` again when its input goes bad while it recovers (it said
    `recovering`), and a prediction it lost is no longer held at its clamp (`unclamped`)."""
    c = _sum({"max_abs_um": 5.0, "max_slew_um_per_s": 100.0, "fault_policy": "hold"}, 1.0, 10.0)
    said: list[str] = []
    c.emit = lambda t, subject, event, reason: said.append(event)
    out = np.zeros(1)
    for t, x in ((0.0, 20.0), (1.0, math.nan), (2.0, 3.0), (3.0, math.nan), (4.0, 3.0)):
        c.run_degraded(np.array([x]), np.array([x == x]), t, out)
        if t == 1.0:
            assert not c.part_clamped[0]  # lost: nothing held at the clamp
    assert said == ["clamped", "unclamped", "fault", "recovering", "fault", "recovering"]
    assert c.part_state[0] == AxisState.RECOVERING


def test_policy_names_round_trip_config_enum_status() -> None:
    """The config's fault_policy names are the enum's (lower case), and each reaches the guard's
    status, the static status and a contribution's limits as the name it was written with."""
    assert get_args(FaultPolicy) == tuple(POLICY_LABELS) == tuple(POLICY_NAMES.values())
    for name in POLICY_LABELS:
        assert Policy.named(name).label == name and POLICY_NAMES[Policy.named(name)] == name
    # the status record's state names are the enum's
    for fields in (AXIS, PART):
        state = next(f for f in fields if f.key == "state")
        assert state.names == tuple(STATE_NAMES[s] for s in AxisState) == ("starting", "normal", "fault", "recovering")
    cfg = GuardConfig(
        fault_policy="ramp_to_zero", axes={"x": {"fault_policy": "disable"}, "y": {"fault_policy": "hold"}}
    )
    g = Guard(cfg, ["x", "y", "z"], Frame(["T"]), ["T"])
    assert [s["policy"] for s in g.get_status().values()] == ["disable", "hold", "ramp_to_zero"]
    assert g.policy == [Policy.DISABLE, Policy.HOLD, Policy.RAMP_TO_ZERO]
    for name in POLICY_LABELS:
        c = _sum({"max_abs_um": 5.0, "max_slew_um_per_s": 1.0, "fault_policy": name}, 1.0, 1.0)
        assert c.limiter.policy == [Policy.named(name)]
        assert c.get_status()["contributions"][0]["limits"]["z"]["fault_policy"] == name


def test_a_config_names_each_policy_and_the_status_shows_it(tmp_path: Any) -> None:
    """From the YAML to the daemon's status: guard and per-axis policies, and a contribution's own."""
    from compd.config import load_config
    from compd.cycle.pipeline import from_config
    from compd.cycle.statusblock import describe_static
    from compd.log import write_log

    write_log(tmp_path / "log.csv", ["t_s", "T"], np.array([[0.0, 20.0], [1.0, 20.0]]))
    cfg = tmp_path / "c.yaml"
    cfg.write_text("""\
loop: {clock: sim, period_s: 1.0}
sources: [{kind: replay, name: log, path: log.csv}]
model:
  contributions:
    - {name: a, kind: mlr, inputs: [T], outputs: [x, z], fault_policy: disable,
       params: {coef_um_per_k: [[1.0, 1.0]], intercept_um: [0.0, 0.0]}}
    - {name: b, kind: mlr, inputs: [T], outputs: [z], params: {coef_um_per_k: [[2.0]], intercept_um: [0.0]}}
guard: {fault_policy: ramp_to_zero, axes: {z: {fault_policy: hold}}}
sink: {kind: pci1756}
""")
    p, _ = from_config(load_config(cfg))
    assert describe_static(p.loop, False)["policy"] == ["ramp_to_zero", "hold"]
    assert p.model.limiter.policy == [Policy.DISABLE, Policy.DISABLE, Policy.HOLD]  # a: x, z; b: z (its axis's)
    assert {a: s["policy"] for a, s in p.guard.get_status().items()} == {"x": "ramp_to_zero", "z": "hold"}
    assert isinstance(p.model, Contributions) and p.model.kind == "contributions"


def test_the_limiter_never_moves_faster_than_its_slew_or_ramp() -> None:
    """The plain rule behind the rest: a normal channel reaches its target at the slew, a faulted
    one under ramp_to_zero goes to 0 at the ramp, and a disabled one is 0 with its enable off."""
    lim = Limiter([10.0, 10.0, 10.0], [2.0, 2.0, 2.0], list(Policy), 0.5, 1.0)
    for k in range(3):
        lim.step(k, 100.0, 0.0, 0.0)  # started: normal, clamped to 10
    for i in range(1, 8):
        for k in range(3):
            lim.step(k, 100.0, 1.0, float(i))
    np.testing.assert_array_equal(lim.value_um, [10.0, 10.0, 10.0])
    assert lim.clamped.all() and lim.all_normal()
    for k in range(3):
        lim.step(k, math.nan, 1.0, 8.0)
    assert list(lim.value_um) == [10.0, 9.5, 0.0] and list(lim.enable) == [True, True, False]
    assert all(lim.state == AxisState.FAULT) and not lim.clamped.any()


def test_a_channel_taken_over_while_recovering_recovers_after_a_whole_wait() -> None:
    """A reload hands the new guard the old one's state (compd.daemon.app.App.adopt): a channel
    taken over while recovering has no start of its wait here; the wait starts at its first step,
    so it goes normal recovery_s later (before, it stayed recovering until it faulted again)."""
    lim = Limiter([10.0], [2.0], [Policy.HOLD], 0.5, 3.0)
    lim.state[0] = AxisState.RECOVERING  # as App.adopt copies it
    lim.value_um[0] = 1.0
    lim.step(0, 1.0, 1.0, 100.0)
    lim.step(0, 1.0, 1.0, 102.0)
    assert lim.state[0] == AxisState.RECOVERING  # 2 s of a 3 s wait
    said = lim.step(0, 1.0, 1.0, 103.0)
    assert lim.state[0] == NORMAL and said & TO_NORMAL

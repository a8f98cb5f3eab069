"""What reaches the machine: plausibility, clamp, slew limit and the fault policy.

Per cycle the guard (1) marks implausible model inputs (range, rate of change,
staleness) in the frame, (2) turns the predicted error into a target correction
(−prediction, clamped), and (3) moves each axis's output toward its target no
faster than the slew limit, or — when an input the axis needs is bad — applies the
axis's fault policy: `hold` the last correction, `ramp_to_zero` at a set rate, or
`disable` (enable bit off). Recovery waits until the inputs have been good for
`recovery_s` and then slews from wherever the output is, so nothing ever steps.
(2) and (3) are compd.cycle.limiter's, one channel per axis: the limiter every
contribution of a sum is limited by too.
An axis the machine holds off (`hold`, set each cycle by compd.cycle.inhibit: inhibited, or
waiting for its reference) targets zero at its slew limit, whatever its state, and
slews back to its target once released.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from compd.core.config import GuardConfig
from compd.core.frame import QUALITY_NAMES, Frame, Quality
from compd.cycle.inhibit import HOLD_NAMES
from compd.cycle.limiter import (
    CLAMPED,
    NORMAL,
    STATE_NAMES,
    TO_FAULT,
    TO_NORMAL,
    TO_RECOVERING,
    UNCLAMPED,
    Limiter,
    Policy,
    clamp_um,
    toward_um,
)

GOOD = int(Quality.GOOD)
STALE = int(Quality.STALE)
OUT_OF_RANGE = int(Quality.OUT_OF_RANGE)
IMPLAUSIBLE = int(Quality.IMPLAUSIBLE)
FROZEN = int(Quality.FROZEN)
NO_DATA = int(Quality.NO_DATA)


class Guard:
    """Stateful per-axis guard. Arrays are allocated once; `update` allocates nothing."""

    def __init__(self, cfg: GuardConfig, axes: list[str], frame: Frame, inputs: list[str]) -> None:
        self.cfg = cfg
        self.axes = list(axes)
        n = len(axes)
        self.max_abs_um = np.array([cfg.clamp_um(a)[0] for a in axes])
        self.slew_um_per_s = np.array([cfg.slew_um_per_s(a) for a in axes])
        # each axis's clamp, slew limit and fault policy (compd.cycle.limiter: its state and output)
        self.limiter = lim = Limiter(
            self.max_abs_um.tolist(),
            self.slew_um_per_s.tolist(),
            [Policy.named((cfg.axes.get(a) and cfg.axes[a].fault_policy) or cfg.fault_policy) for a in axes],
            cfg.ramp_um_per_s,
            cfg.recovery_s,
        )
        self.policy = lim.policy
        self._n_axes = n
        self._max_abs = lim.max_abs_um
        self._slew = lim.slew_um_per_s
        self.out_um = lim.value_um
        self.enable = lim.enable
        self.target_um = lim.target_um
        self.state = lim.state
        # the target is held at ±max_abs_um this cycle: the model asks for more than the clamp lets
        # through (an event `clamped` when it starts, `unclamped` when it ends)
        self.clamped = lim.clamped  # for the status record
        self._clamped = lim.clamped_list  # the same, as the cycle reads it (a list: no numpy scalar per cycle)
        # why the machine holds an axis off this cycle (compd.cycle.inhibit: 0 none, 1 inhibited,
        # 2 waiting for reference); written before `update`, which ramps a held axis to 0
        self.hold = np.zeros(n, dtype=np.uint8)
        self._held = np.zeros(n, dtype=np.uint8)
        self._last_t = math.nan
        self.dt_s = 0.0  # the time the last update licensed (what the codec may spend too)
        # plausibility of the model inputs
        self.input_idx = frame.indices(inputs)
        limits = [cfg.signals.get(name) for name in inputs]
        self._min = np.array([lm.min if lm else -math.inf for lm in limits])
        self._max = np.array([lm.max if lm else math.inf for lm in limits])
        self._rate = np.array([lm.max_rate_per_s if lm and lm.max_rate_per_s else math.inf for lm in limits])
        self._rate_allow = np.array([lm.rate_allowance if lm else 0.0 for lm in limits])
        self._stale = np.array([lm.stale_after_s if lm and lm.stale_after_s else cfg.stale_after_s for lm in limits])
        self._frozen_after = np.array([lm.frozen_after_s if lm and lm.frozen_after_s else math.inf for lm in limits])
        self._frozen_band = np.array([lm.frozen_band if lm else 0.0 for lm in limits])
        self._moved_val = np.full(len(inputs), math.nan)  # value at the last real change
        self._moved_t = np.full(len(inputs), -math.inf)  # time of the last real change
        self.max_dt_s = math.inf  # a cycle never licenses more slew than this much time
        self._prev_val = np.full(len(inputs), math.nan)
        self._prev_t = np.full(len(inputs), math.nan)
        self._has_rate = bool(np.isfinite(self._rate).any())
        # a signal without a rate limit beside one with: a limit no change reaches, finite so
        # that × 0 s (the same sample again) is 0, not inf × 0 = NaN and a numpy warning
        self._rate[~np.isfinite(self._rate)] = 1e200
        self._has_frozen = bool(np.isfinite(self._frozen_after).any())
        n_in = len(inputs)
        self._v = np.zeros(n_in)
        self._q = np.zeros(n_in, dtype=np.uint8)
        self._st = np.zeros(n_in)
        self._age = np.zeros(n_in)
        self._dt = np.zeros(n_in)
        self._m = np.zeros(n_in, dtype=bool)
        self._fin = np.zeros(n_in, dtype=bool)
        self._new = np.zeros(n_in, dtype=bool)
        self._tmp = np.zeros(n_in, dtype=bool)
        self._tmp2 = np.zeros(n_in, dtype=bool)
        self.inputs_ok = False
        self.degraded = False
        self.bad_input: int = -1  # index into inputs of the first bad one, -1 if none
        self.faults: dict[str, int] = {}
        self.events: list[tuple[float, str, str, str]] = []  # (t, subject, event, reason)
        self._input_names = list(inputs)
        self._was_bad = np.zeros(len(inputs), dtype=bool)
        # before its first sample an input is waiting, not bad: no event, until it has had no
        # sample for its staleness limit since the first check (then `bad no_data`, a fault)
        self._waiting = np.ones(len(inputs), dtype=bool)
        self._any_waiting = len(inputs) > 0
        self._start_s = math.nan

    # ------------------------------------------------------------ plausibility
    def check_inputs(self, frame: Frame, now_s: float) -> bool:
        """Mark implausible inputs in the frame; True when every model input is good.

        Vectorised over the inputs with preallocated buffers (no allocation when
        nothing changes); events are recorded only when an input changes state.
        """
        idx = self.input_idx
        v, q, st, m, tmp = self._v, self._q, self._st, self._m, self._tmp
        np.take(frame.values, idx, out=v)
        np.take(frame.quality, idx, out=q)
        np.take(frame.stamp_s, idx, out=st)
        np.equal(q, GOOD, out=m)  # m: still good
        # not finite → implausible
        np.isfinite(v, out=self._fin)
        np.logical_not(self._fin, out=tmp)
        np.logical_and(tmp, m, out=tmp)
        q[tmp] = IMPLAUSIBLE
        np.logical_and(m, self._fin, out=m)
        # out of the configured range
        np.less(v, self._min, out=tmp)
        np.logical_or(tmp, np.greater(v, self._max, out=self._tmp2), out=tmp)
        np.logical_and(tmp, m, out=tmp)
        q[tmp] = OUT_OF_RANGE
        np.logical_and(m, np.logical_not(tmp, out=tmp), out=m)
        # stale: sampled longer ago than the limit
        np.subtract(now_s, st, out=self._age)
        np.greater(self._age, self._stale, out=tmp)
        np.logical_and(tmp, m, out=tmp)
        q[tmp] = STALE
        np.logical_and(m, np.logical_not(tmp, out=tmp), out=m)
        if self._has_rate or self._has_frozen:
            new = self._new  # a new sample (NaN prev_t: the first one is new)
            np.less_equal(st, self._prev_t, out=new)
            np.logical_not(new, out=new)
            np.logical_and(new, m, out=new)
            if self._has_rate:  # rate of change against the last accepted sample
                np.subtract(st, self._prev_t, out=self._dt)
                np.multiply(self._rate, self._dt, out=self._dt)
                np.add(self._dt, self._rate_allow, out=self._dt)
                np.subtract(v, self._prev_val, out=self._age)
                np.abs(self._age, out=self._age)
                np.greater(self._age, self._dt, out=tmp)  # False where prev is NaN
                np.logical_and(tmp, new, out=tmp)
                q[tmp] = IMPLAUSIBLE
                np.logical_and(m, np.logical_not(tmp, out=tmp), out=m)
                np.logical_and(new, m, out=new)
            np.copyto(self._prev_val, v, where=new)
            np.copyto(self._prev_t, st, where=new)
            if self._has_frozen:  # frozen: no real change for frozen_after_s while others moved
                moved = self._tmp2
                np.subtract(v, self._moved_val, out=self._age)
                np.abs(self._age, out=self._age)
                np.less_equal(self._age, self._frozen_band, out=moved)  # False where NaN
                np.logical_not(moved, out=moved)
                np.logical_and(moved, new, out=moved)
                np.copyto(self._moved_val, v, where=moved)
                np.copyto(self._moved_t, now_s, where=moved)
                np.subtract(now_s, self._frozen_after, out=self._dt)
                np.less(self._moved_t, self._dt, out=tmp)
                np.logical_and(tmp, m, out=tmp)
                if tmp.any():
                    for j in np.flatnonzero(tmp):
                        if self._others_moved(int(j), float(self._dt[j])):
                            q[j] = FROZEN
                            m[j] = False
        frame.quality[idx] = q
        ok = bool(m.all())
        np.logical_not(m, out=tmp)  # tmp: bad now
        report = tmp  # bad and not waiting for its first sample
        if self._any_waiting:
            self._check_waiting(q, m, now_s)
            report = self._tmp2
            np.logical_not(self._waiting, out=report)
            np.logical_and(report, tmp, out=report)
        if not np.array_equal(report, self._was_bad):
            for j in np.flatnonzero(report != self._was_bad):
                if report[j]:
                    self._event(now_s, self._input_names[j], "bad", QUALITY_NAMES.get(int(q[j]), "?"))
                else:
                    self._event(now_s, self._input_names[j], "good", "recovered")
            self._was_bad[:] = report
        self.inputs_ok = ok
        self.bad_input = -1 if ok else int(np.argmax(tmp))
        return ok

    def plain_rows(self, values: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Replay: the rows (of the model inputs `values`, rows × inputs, stamped `t_s`) that
        pass every check whatever came before, provided the row before passed them all:
        finite, in range, within the rate limit of the row before (`check_inputs`'s
        arithmetic), and stamped later than the row before and earlier than the next (a
        repeated stamp is a sample seen twice). None when a frozen-input limit is set:
        that check looks further back than one row."""
        n = len(t_s)
        if self._has_frozen or not bool((self._stale >= 0).all()):
            return np.zeros(n, dtype=bool)
        good = np.isfinite(values) & ~np.less(values, self._min) & ~np.greater(values, self._max)
        if self._has_rate and n > 1:
            lim = np.add(np.multiply(self._rate, np.subtract(t_s[1:], t_s[:-1])[:, None]), self._rate_allow)
            good[1:] &= ~np.greater(np.abs(np.subtract(values[1:], values[:-1])), lim)
        plain = good.all(axis=1)
        rises = np.diff(t_s) > 0
        plain[1:] &= rises
        plain[:-1] &= rises
        return plain

    def passed(self, values: np.ndarray, t_s: float) -> None:
        """Replay: a row of `plain_rows` that ran without `check_inputs`, after rows that all
        passed: the guard as `check_inputs` would have left it (that row the last sample of
        every input, every input good)."""
        self._prev_val[:] = values
        self._prev_t[:] = t_s
        self.inputs_ok = True
        self.bad_input = -1

    def _check_waiting(self, q: np.ndarray, good: np.ndarray, now_s: float) -> None:
        """Start-up only: an input stops waiting at its first good sample, at any quality but
        no_data, or when it has had none for its staleness limit since the first check."""
        if self._start_s != self._start_s:
            self._start_s = now_s
        for j in np.flatnonzero(self._waiting):
            if good[j] or q[j] != NO_DATA or now_s - self._start_s > self._stale[j]:
                self._waiting[j] = False
        self._any_waiting = bool(self._waiting.any())

    def _others_moved(self, j: int, since_s: float) -> bool:
        """Did another model input change after `since_s`? (True when there is no other.)"""
        n = self._moved_t.shape[0]
        if n == 1:
            return True
        return any(k != j and self._moved_t[k] > since_s for k in range(n))

    def clock_jump(self, now_s: float, period_s: float) -> None:
        """The loop clock stepped: it moved by something other than elapsed time (a simulated
        or plant clock set ahead, time going backwards; `clock_stepped`). Event `jump` of
        subject `clock` (logged `clock_jump`); the next cycle may move the output by one
        period's slew, not by the whole gap."""
        gap = now_s - self._last_t
        if gap == gap:
            self._event(now_s, "clock", "jump", f"{gap:+.3f} s since the last cycle")
        self._last_t = now_s - period_s

    def stall(self, now_s: float, period_s: float, late_s: float, gap_s: float) -> None:
        """The loop did not run for a while (an overloaded machine, a stopped process) on a
        clock that did not step: it woke `late_s` late, or `gap_s` after the cycle before (a
        stall during that cycle's work). Event `stall` of subject `loop` (logged `loop_stall`,
        counted in `faults` as `stall:loop`); as after a clock jump, the next cycle may move the
        output by one period's slew, not by the whole gap."""
        why = f"woke {late_s:.3f} s late" if late_s > 0.5 * gap_s else f"{gap_s:.3f} s since the last cycle"
        self._event(now_s, "loop", "stall", why, key="stall:loop")
        self._last_t = now_s - period_s

    @staticmethod
    def clock_stepped(gap_s: float, elapsed_s: float, rate: float, simulated: bool, jump_s: float) -> bool:
        """Whether a gap of `gap_s` on the loop clock between two cycles, over `elapsed_s` of
        elapsed (monotonic) time, was a step of the clock rather than a stall of the loop.

        A stall (the process did not run) moves a clock that follows elapsed time as far as
        elapsed time moved: `rate` × `elapsed_s` (`rate`: loop-clock seconds per elapsed
        second, 1 on the wall clock, a plant's speed-up on a plant's clock). A step moves it
        by something else: time going backwards, or a gap elapsed time does not explain (off
        by more than `jump_s` plus a quarter of the advance expected). A simulated clock's
        time does not elapse by itself (its wait sets it to the deadline): any gap on it is
        a step."""
        if simulated or gap_s < 0.0:
            return True
        expected_s = max(rate, 0.0) * elapsed_s
        return abs(gap_s - expected_s) > jump_s + 0.25 * expected_s

    def event(self, t: float, subject: str, event: str, reason: str) -> None:
        """Record an event of a stage before the guard (a contribution's fault, clamp, recovery)."""
        self._event(t, subject, event, reason, key=event if event in ("clamped", "unclamped") else "")

    def _event(self, t: float, subject: str, event: str, reason: str, key: str | None = "") -> None:
        """Record an event; `faults` counts it under `key` (default "event:reason"; None: not a
        fault, not counted)."""
        if key is not None:
            key = key or f"{event}:{reason}"
            self.faults[key] = self.faults.get(key, 0) + 1
        self.events.append((t, subject, event, reason))
        if len(self.events) > 1000:
            del self.events[:500]

    # ----------------------------------------------------------------- output
    def update(self, pred_um: np.ndarray, inputs_ok: bool, now_s: float, degraded: bool = False) -> None:
        """Advance every axis by one cycle; results in `out_um` and `enable`.

        `degraded`: some model inputs are bad and the model predicts from the others;
        an axis it could serve has a finite prediction, the others NaN (→ fault).
        """
        if degraded != self.degraded:
            self.degraded = degraded
            self._event(now_s, "model", "degraded" if degraded else "complete", "inputs")
        dt = now_s - self._last_t if self._last_t == self._last_t else 0.0
        if dt < 0:
            dt = 0.0  # a clock that went backwards never licenses a step
        elif dt > self.max_dt_s:
            dt = self.max_dt_s
        self._last_t = now_s
        self.dt_s = dt
        lim = self.limiter
        hold, held = self.hold, self._held
        for a in range(self._n_axes):
            if hold[a] != held[a]:
                self._hold_event(now_s, a, int(hold[a]), int(held[a]))
                held[a] = hold[a]
            if hold[a]:  # held off by the machine: to 0 at the slew, never a step
                if lim.held_off(a, dt):
                    self._said(now_s, a, UNCLAMPED, 0.0, inputs_ok)
                continue
            p = float(pred_um[a])
            said = lim.step(a, -p if inputs_ok else math.nan, dt, now_s)
            if said:
                self._said(now_s, a, said, p, inputs_ok)

    def _said(self, now_s: float, a: int, said: int, pred_um: float, inputs_ok: bool) -> None:
        """The events of what the limiter said of axis `a` this cycle (its bits), in order."""
        if said & (CLAMPED | UNCLAMPED):
            self._clamp_event(now_s, a, pred_um, bool(said & CLAMPED))
        if said & TO_RECOVERING:
            self._event(now_s, self.axes[a], "recovering", "inputs good")
        if said & TO_NORMAL:
            self._event(now_s, self.axes[a], "normal", "recovered")
        if said & TO_FAULT:
            self._event(now_s, self.axes[a], "fault", "prediction not finite" if inputs_ok else "input bad")

    def update_rows(
        self,
        pred_um: np.ndarray,
        inputs_ok: np.ndarray,
        t_s: np.ndarray,
        degraded: np.ndarray,
        hold: np.ndarray | None,
        out_um: np.ndarray,
        enable: np.ndarray,
        state: np.ndarray,
        dt_s: np.ndarray,
    ) -> None:
        """`update` at every row of a replay: row i is `hold` ← hold[i] (None: never held),
        then update(pred_um[i], inputs_ok[i], t_s[i], degraded[i]); the results (out_um,
        enable, state, dt_s) into row i of the arrays given.

        A row in which every axis is NORMAL and stays so (inputs good, a finite prediction,
        not held, the degraded flag as it was) takes a float-only path with `update`'s
        arithmetic; any other row calls `update` itself."""
        n_axes = self._n_axes
        lim, slew, max_dt = self._max_abs, self._slew, self.max_dt_s
        pred, degs, ts = pred_um.tolist(), degraded.tolist(), t_s.tolist()
        holds = hold.tolist() if hold is not None else None
        # the rows the float path may take, as far as the row alone says: inputs good, every
        # prediction finite, nothing held
        plain = np.logical_and(inputs_ok, np.isfinite(pred_um).all(axis=1))
        if hold is not None:
            np.logical_and(plain, ~hold.any(axis=1), out=plain)
        plains = plain.tolist()
        cols: list[list[float]] = [[0.0] * len(ts) for _ in range(n_axes)]
        dts = [0.0] * len(ts)
        enable[:] = True  # what a NORMAL axis has; the rows `update` runs are written below
        state[:] = NORMAL
        out = self.out_um.tolist()
        target = self.target_um.tolist()
        last_t, dt = self._last_t, self.dt_s
        was_degraded = self.degraded
        normal = self._all_normal()
        axes = range(n_axes)
        limiter = self.limiter
        clamped = self._clamped  # the limiter flips it: the float path reads it in place
        for i, now in enumerate(ts):
            if normal and plains[i] and degs[i] == was_degraded:
                p = pred[i]
                # update's arithmetic for axes in NORMAL: the licensed time, then the slew
                dt = now - last_t if last_t == last_t else 0.0
                if dt < 0:
                    dt = 0.0
                elif dt > max_dt:
                    dt = max_dt
                last_t = now
                for a in axes:  # the limiter's step of a NORMAL axis, on floats
                    want = -p[a]
                    tg = clamp_um(want, lim[a])
                    if (tg != want) != clamped[a]:
                        self._clamp_event(now, a, p[a], limiter.flip_clamped(a) == CLAMPED)
                    target[a] = tg
                    o = toward_um(out[a], tg, slew[a] * dt)
                    out[a] = o
                    cols[a][i] = o
                dts[i] = dt
                continue
            # anything else: `update` itself, on the state the float path left
            self.out_um[:] = out
            self.target_um[:] = target
            if normal:
                self.enable[:] = True
            self._last_t, self.dt_s = last_t, dt
            if holds is not None:
                self.hold[:] = holds[i]
            self.update(pred_um[i], bool(inputs_ok[i]), now, degraded=degs[i])
            out = self.out_um.tolist()
            target = self.target_um.tolist()
            last_t, dt = self._last_t, self.dt_s
            was_degraded = self.degraded
            normal = self._all_normal()
            for a in range(n_axes):
                cols[a][i] = out[a]
            dts[i] = dt
            enable[i] = self.enable
            state[i] = self.state
        self.out_um[:] = out
        self.target_um[:] = target
        if normal:
            self.enable[:] = True
        self._last_t, self.dt_s = last_t, dt
        for a in range(n_axes):
            out_um[:, a] = cols[a]
        dt_s[:] = dts

    def _all_normal(self) -> bool:
        """Every axis NORMAL and none held off (what the float path of `update_rows` needs)."""
        return self.limiter.all_normal() and not self._held.any()

    def _clamp_event(self, now_s: float, a: int, pred_um: float, on: bool) -> None:
        """The axis's target started (`on`) or stopped being held at the clamp: the event."""
        lim = self._max_abs[a]
        if on:
            self._event(
                now_s,
                self.axes[a],
                "clamped",
                f"the model predicts {pred_um:.1f} um, beyond the clamp of {lim:g} um",
                key="clamped",
            )
        else:
            self._event(
                now_s, self.axes[a], "unclamped", f"the prediction is inside the clamp of {lim:g} um", key="unclamped"
            )

    def _hold_event(self, now_s: float, a: int, hold: int, was: int) -> None:
        if hold:
            self._event(now_s, self.axes[a], "held", str(HOLD_NAMES[hold]))
        else:
            self._event(now_s, self.axes[a], "released", str(HOLD_NAMES[was]))

    def seed(self, a: int, um: float, now_s: float) -> None:
        """What the machine applies on axis `a` now (µm, read back by the sink at its start or after
        its link was restored): the output goes on from there at the slew, never a step. Before the
        model's first prediction it goes to 0 at `ramp_um_per_s`."""
        if not math.isfinite(um):
            return
        self.limiter.seed(a, um)
        self._event(
            now_s, self.axes[a], "synced", f"the machine applies {um:+.3f} um: the output goes on from there", key=None
        )

    def safe(self) -> None:
        self.limiter.safe()

    def get_status(self) -> dict[str, Any]:
        return {
            a: {
                "correction_um": float(self.out_um[i]),
                "target_um": float(self.target_um[i]),
                "enable": bool(self.enable[i]),
                "state": STATE_NAMES[int(self.state[i])],
                "policy": self.policy[i].label,
                "degraded": self.degraded,
                "inhibit": HOLD_NAMES[int(self.hold[i])],
            }
            for i, a in enumerate(self.axes)
        }

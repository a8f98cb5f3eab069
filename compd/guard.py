"""What reaches the machine: plausibility, clamp, slew limit and the fault policy (SPEC §1).

Per cycle the guard (1) marks implausible model inputs (range, rate of change,
staleness) in the frame, (2) turns the predicted error into a target correction
(−prediction, clamped), and (3) moves each axis's output toward its target no
faster than the slew limit, or — when an input the axis needs is bad — applies the
axis's fault policy: `hold` the last correction, `ramp_to_zero` at a set rate, or
`disable` (enable bit off). Recovery waits until the inputs have been good for
`recovery_s` and then slews from wherever the output is, so nothing ever steps.
"""

from __future__ import annotations

import enum
import math
from typing import Any

import numpy as np

from compd.config import GuardConfig
from compd.frame import Frame, Quality


class AxisState(enum.IntEnum):
    STARTING = 0  # no good prediction yet: output 0
    NORMAL = 1
    FAULT = 2
    RECOVERING = 3  # inputs good again, waiting recovery_s


STATE_NAMES = {s.value: s.name.lower() for s in AxisState}
POLICIES = ("hold", "ramp_to_zero", "disable")


class Guard:
    """Stateful per-axis guard. Arrays are allocated once; `update` allocates nothing."""

    def __init__(self, cfg: GuardConfig, axes: list[str], frame: Frame, inputs: list[str]) -> None:
        self.cfg = cfg
        self.axes = list(axes)
        n = len(axes)
        self.max_abs_um = np.array(
            [(cfg.axes.get(a) and cfg.axes[a].max_abs_um) or cfg.max_abs_um for a in axes]
        )
        self.slew_um_per_s = np.array(
            [(cfg.axes.get(a) and cfg.axes[a].max_slew_um_per_s) or cfg.max_slew_um_per_s for a in axes]
        )
        self.policy = [
            POLICIES.index((cfg.axes.get(a) and cfg.axes[a].fault_policy) or cfg.fault_policy)
            for a in axes
        ]
        self.out_um = np.zeros(n)
        self.enable = np.zeros(n, dtype=bool)
        self.target_um = np.zeros(n)
        self.state = np.full(n, AxisState.STARTING, dtype=np.uint8)
        self._good_since = np.full(n, math.nan)
        self._last_t = math.nan
        # plausibility of the model inputs
        self.input_idx = frame.indices(inputs)
        lim = [cfg.signals.get(name) for name in inputs]
        self._min = np.array([lm.min if lm else -math.inf for lm in lim])
        self._max = np.array([lm.max if lm else math.inf for lm in lim])
        self._rate = np.array(
            [lm.max_rate_per_s if lm and lm.max_rate_per_s else math.inf for lm in lim]
        )
        self._rate_allow = np.array([lm.rate_allowance if lm else 0.0 for lm in lim])
        self._stale = np.array(
            [lm.stale_after_s if lm and lm.stale_after_s else cfg.stale_after_s for lm in lim]
        )
        self._frozen_after = np.array(
            [lm.frozen_after_s if lm and lm.frozen_after_s else math.inf for lm in lim]
        )
        self._frozen_band = np.array([lm.frozen_band if lm else 0.0 for lm in lim])
        self._moved_val = np.full(len(inputs), math.nan)  # value at the last real change
        self._moved_t = np.full(len(inputs), -math.inf)  # time of the last real change
        self.max_dt_s = math.inf  # a cycle never licenses more slew than this much time
        self._prev_val = np.full(len(inputs), math.nan)
        self._prev_t = np.full(len(inputs), math.nan)
        self.inputs_ok = False
        self.degraded = False
        self.bad_input: int = -1  # index into inputs of the first bad one, -1 if none
        self.faults: dict[str, int] = {}
        self.events: list[tuple[float, str, str, str]] = []  # (t, subject, event, reason)
        self._input_names = list(inputs)
        self._was_bad = np.zeros(len(inputs), dtype=bool)

    # ------------------------------------------------------------ plausibility
    def check_inputs(self, frame: Frame, now_s: float) -> bool:
        """Mark implausible inputs in the frame; True when every model input is good."""
        idx = self.input_idx
        ok = True
        first_bad = -1
        for j in range(idx.shape[0]):
            i = idx[j]
            q = frame.quality[i]
            v = frame.values[i]
            if q == Quality.GOOD:
                if not math.isfinite(v):
                    q = Quality.IMPLAUSIBLE
                elif v < self._min[j] or v > self._max[j]:
                    q = Quality.OUT_OF_RANGE
                elif now_s - frame.stamp_s[i] > self._stale[j]:
                    q = Quality.STALE
                else:
                    pt = self._prev_t[j]
                    if not frame.stamp_s[i] <= pt:  # a new sample (pt is NaN at first)
                        allowed = self._rate[j] * (frame.stamp_s[i] - pt) + self._rate_allow[j]
                        if pt == pt and abs(v - self._prev_val[j]) > allowed:
                            q = Quality.IMPLAUSIBLE
                        else:
                            self._prev_val[j] = v
                            self._prev_t[j] = frame.stamp_s[i]
                            if not abs(v - self._moved_val[j]) <= self._frozen_band[j]:
                                self._moved_val[j] = v
                                self._moved_t[j] = now_s
                    since = now_s - self._frozen_after[j]
                    if q == Quality.GOOD and self._moved_t[j] < since and self._others_moved(j, since):
                        q = Quality.FROZEN
                frame.quality[i] = q
            if q != Quality.GOOD:
                if not self._was_bad[j]:
                    self._was_bad[j] = True
                    self._event(now_s, self._input_names[j], "bad", Quality(q).name.lower())
                if ok:
                    first_bad = j
                ok = False
            elif self._was_bad[j]:
                self._was_bad[j] = False
                self._event(now_s, self._input_names[j], "good", "recovered")
        self.inputs_ok = ok
        self.bad_input = first_bad
        return ok

    def _others_moved(self, j: int, since_s: float) -> bool:
        """Did another model input change after `since_s`? (True when there is no other.)"""
        n = self._moved_t.shape[0]
        if n == 1:
            return True
        return any(k != j and self._moved_t[k] > since_s for k in range(n))

    def clock_jump(self, now_s: float, period_s: float) -> None:
        """The loop woke far too late (clock jump, suspend, stall): the next cycle may
        move the output by one period's slew, not by the whole gap."""
        gap = now_s - self._last_t
        if gap == gap:
            self._event(now_s, "clock", "jump", f"{gap:+.3f} s since the last cycle")
        self._last_t = now_s - period_s

    def _event(self, t: float, subject: str, event: str, reason: str) -> None:
        key = f"{event}:{reason}"
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
        cfg = self.cfg
        for a in range(self.out_um.shape[0]):
            p = pred_um[a]
            good = inputs_ok and math.isfinite(p)
            lim = self.max_abs_um[a]
            target = -p if good else 0.0
            target = lim if target > lim else (-lim if target < -lim else target)
            self.target_um[a] = target
            st = self.state[a]
            if good:
                if st == AxisState.FAULT:
                    self.state[a] = st = AxisState.RECOVERING
                    self._good_since[a] = now_s
                    self._event(now_s, self.axes[a], "recovering", "inputs good")
                if st == AxisState.RECOVERING and now_s - self._good_since[a] >= cfg.recovery_s:
                    self.state[a] = st = AxisState.NORMAL
                    self._event(now_s, self.axes[a], "normal", "recovered")
                if st == AxisState.STARTING:
                    self.state[a] = st = AxisState.NORMAL
            elif st != AxisState.FAULT:
                if st != AxisState.STARTING:
                    reason = "prediction not finite" if inputs_ok else "input bad"
                    self._event(now_s, self.axes[a], "fault", reason)
                    if self.policy[a] == 2 and self.enable[a]:
                        self.out_um[a] = 0.0
                    self.state[a] = st = AxisState.FAULT
                else:
                    self.enable[a] = False
                    continue
            out = self.out_um[a]
            if st == AxisState.NORMAL:
                step = self.slew_um_per_s[a] * dt
                d = target - out
                out = out + (step if d > step else (-step if d < -step else d))
                self.enable[a] = True
            elif st == AxisState.FAULT or st == AxisState.RECOVERING:
                pol = self.policy[a]
                if pol == 1:  # ramp_to_zero
                    step = cfg.ramp_um_per_s * dt
                    out = out - step if out > step else (out + step if out < -step else 0.0)
                    self.enable[a] = True
                elif pol == 2:  # disable
                    out = 0.0
                    self.enable[a] = False
                # hold: out unchanged
            self.out_um[a] = out

    def safe(self) -> None:
        self.out_um[:] = 0.0
        self.enable[:] = False

    def get_status(self) -> dict[str, Any]:
        return {
            a: {
                "correction_um": float(self.out_um[i]),
                "target_um": float(self.target_um[i]),
                "enable": bool(self.enable[i]),
                "state": STATE_NAMES[int(self.state[i])],
                "policy": POLICIES[self.policy[i]],
                "degraded": self.degraded,
            }
            for i, a in enumerate(self.axes)
        }

"""One output limiter: a clamp, a slew limit and a fault policy, per channel, for the guard and each contribution.

A channel is an output that follows a wanted value: an axis of the guard (compd.cycle.guard: it
wants −prediction) or a contribution on one of its axes (compd.cycle.contributions: it wants its
model's prediction). Each step the want is clamped to ±`max_abs_um` (the target) and the output
moves toward it by at most `max_slew_um_per_s` × dt, so it never steps. When the want is lost (NaN:
an input bad, a prediction not finite) the channel faults and its `Policy` decides the output:
`hold` the last value, `ramp_to_zero` at `ramp_um_per_s`, or `disable` (0, enable off). Back to
normal once the want has been there for `recovery_s`, slewing from wherever the output stands.
Before its first want (STARTING) a channel takes what it was seeded with (what the machine
applied) to 0 at the ramp.

The policies and states are enums whose lower-case names are the config's and the status's
strings (`fault_policy: ramp_to_zero`, `state: recovering`). `step` allocates nothing and says
what happened as bits (`CLAMPED`, `FAULT`, ...), for the caller to word its own events. The
arithmetic is two functions, `clamp_um` and `toward_um`: the replay's float path
(compd.cycle.guard.Guard.update_rows) calls them for rows in which every channel is NORMAL, and
gives the cycle's numbers bit for bit.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence

import numpy as np


class AxisState(enum.IntEnum):
    """Where a channel (an axis, or a contribution on it) is; the status shows the lower-case name."""

    STARTING = 0  # no want yet: what it was seeded with to 0 at the ramp
    NORMAL = 1  # following its target at the slew
    FAULT = 2  # the want lost: the policy decides
    RECOVERING = 3  # the want back, waiting recovery_s (the policy still decides)


class Policy(enum.IntEnum):
    """What a faulted channel does (the config's `fault_policy`: the lower-case name)."""

    HOLD = 0  # the last value
    RAMP_TO_ZERO = 1  # to 0 at ramp_um_per_s, enabled
    DISABLE = 2  # 0 at once, enable off (a contribution: its axis's own policy)

    @classmethod
    def named(cls, name: str) -> Policy:
        """The policy the config names (`hold`, `ramp_to_zero`, `disable`)."""
        return cls[name.upper()]

    @property
    def label(self) -> str:
        """The config's and the status's name of the policy."""
        return self.name.lower()


STATE_NAMES = {s.value: s.name.lower() for s in AxisState}
POLICY_NAMES = {p.value: p.label for p in Policy}

STARTING, NORMAL, FAULT, RECOVERING = (int(s) for s in AxisState)  # plain ints: the cycle compares them
HOLD, RAMP_TO_ZERO, DISABLE = (int(p) for p in Policy)

# what a step did, as bits of its return value (the caller words the events)
CLAMPED = 1  # the target started being held at ±max_abs_um
UNCLAMPED = 2  # ... and stopped
TO_FAULT = 4  # the want was lost: FAULT
TO_RECOVERING = 8  # the want is back: RECOVERING
TO_NORMAL = 16  # recovered: NORMAL after RECOVERING


def clamp_um(want_um: float, max_abs_um: float) -> float:
    """`want_um` held within ±`max_abs_um`."""
    if want_um > max_abs_um or want_um < -max_abs_um:
        return max_abs_um if want_um > 0 else -max_abs_um
    return want_um


def toward_um(value_um: float, target_um: float, step_um: float) -> float:
    """`value_um` moved toward `target_um` by at most `step_um` (≥ 0): there when within it."""
    d = target_um - value_um
    return value_um + (step_um if d > step_um else (-step_um if d < -step_um else d))


class Limiter:
    """Channels limited alike, each with its clamp, slew limit and policy; ramp and recovery shared.

    The per-channel results are arrays made once (`value_um`, `target_um`, `enable`, `state`,
    `clamped`) that the status record copies; the cycle reads the limits as floats from lists."""

    def __init__(
        self,
        max_abs_um: Sequence[float],
        slew_um_per_s: Sequence[float],
        policy: Sequence[Policy],
        ramp_um_per_s: float,
        recovery_s: float,
    ) -> None:
        n = len(max_abs_um)
        if not len(slew_um_per_s) == len(policy) == n:
            raise ValueError("a clamp, a slew limit and a policy per channel")
        self.max_abs_um = [float(v) for v in max_abs_um]
        self.slew_um_per_s = [float(v) for v in slew_um_per_s]
        self.policy = [Policy(p) for p in policy]
        self._policy = [int(p) for p in self.policy]  # the same, as the cycle compares them
        self.ramp_um_per_s = float(ramp_um_per_s)
        self.recovery_s = float(recovery_s)
        self.value_um = np.zeros(n)  # the output
        self.target_um = np.zeros(n)  # the want, clamped (0 while it is lost)
        self.enable = np.zeros(n, dtype=bool)
        self.state = np.full(n, STARTING, dtype=np.uint8)
        self.clamped = np.zeros(n, dtype=bool)  # for the status record
        self.clamped_list = [False] * n  # the same, as the cycle reads it (no numpy scalar per step)
        self._good_since = [math.nan] * n

    def __len__(self) -> int:
        return len(self.max_abs_um)

    def step(self, k: int, want_um: float, dt_s: float, now_s: float) -> int:
        """Channel `k` one step of `dt_s` at `now_s` toward `want_um` (NaN or ±inf: lost this step):
        the target, the state, the output and the enable bit; returns what happened (bits)."""
        said = 0
        good = want_um - want_um == 0.0  # finite
        target = clamp_um(want_um, self.max_abs_um[k]) if good else 0.0
        if (good and target != want_um) != self.clamped_list[k]:
            said = self.flip_clamped(k)
        self.target_um[k] = target
        st = int(self.state[k])
        if good:
            if st == FAULT:
                self.state[k] = st = RECOVERING
                self._good_since[k] = now_s
                said |= TO_RECOVERING
            if st == RECOVERING and self._good_since[k] != self._good_since[k]:
                # recovering without a start (an axis a reload took over while it recovered): the
                # wait starts now, never shorter than recovery_s
                self._good_since[k] = now_s
            if st == RECOVERING and now_s - self._good_since[k] >= self.recovery_s:
                self.state[k] = st = NORMAL
                said |= TO_NORMAL
            if st == STARTING:
                self.state[k] = st = NORMAL
        elif st != FAULT:
            if st != STARTING:
                self.state[k] = st = FAULT
                said |= TO_FAULT
            else:  # no want yet: what it was seeded with to 0 at the ramp
                value = float(self.value_um[k])
                if value != 0.0:
                    value = toward_um(value, 0.0, self.ramp_um_per_s * dt_s)
                    self.value_um[k] = value
                self.enable[k] = value != 0.0
                return said
        value = float(self.value_um[k])
        if st == NORMAL:
            value = toward_um(value, target, self.slew_um_per_s[k] * dt_s)
            self.enable[k] = True
        else:  # FAULT or RECOVERING: the channel's policy
            pol = self._policy[k]
            if pol == RAMP_TO_ZERO:
                value = toward_um(value, 0.0, self.ramp_um_per_s * dt_s)
                self.enable[k] = True
            elif pol == DISABLE:
                value = 0.0
                self.enable[k] = False
            # HOLD: the value (and the enable bit) as they were
        self.value_um[k] = value
        return said

    def held_off(self, k: int, dt_s: float) -> int:
        """Channel `k` held off by the machine this step (compd.cycle.inhibit): target 0, the output
        to 0 at its slew (never a step), enabled while not 0, its state kept; returns UNCLAMPED
        when that ends a clamp."""
        said = self.flip_clamped(k) if self.clamped_list[k] else 0
        self.target_um[k] = 0.0
        value = toward_um(float(self.value_um[k]), 0.0, self.slew_um_per_s[k] * dt_s)
        self.value_um[k] = value
        self.enable[k] = value != 0.0
        return said

    def flip_clamped(self, k: int) -> int:
        """Channel `k`'s target starts (or stops) being held at its clamp: the flag; CLAMPED or UNCLAMPED."""
        self.clamped_list[k] = on = not self.clamped_list[k]
        self.clamped[k] = on
        return CLAMPED if on else UNCLAMPED

    def seed(self, k: int, value_um: float) -> None:
        """What the machine applies on channel `k` now: the output goes on from there at the slew
        (before the first want: to 0 at the ramp, enabled while not 0)."""
        self.value_um[k] = value_um
        if int(self.state[k]) == STARTING:
            self.enable[k] = value_um != 0.0

    def all_normal(self) -> bool:
        """Every channel NORMAL (what a float path of NORMAL steps needs)."""
        return bool((self.state == NORMAL).all())

    def safe(self) -> None:
        """Every output 0, every enable off."""
        self.value_um[:] = 0.0
        self.enable[:] = False

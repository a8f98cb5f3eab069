"""Several contributions summed per axis, each a model on its own inputs with its own clamp, slew and fault policy.

A machine's axis has several heat sources: a vertical machining centre's Z grows with the
spindle (its own model on its own sensor) and with the column (a structure model on column
sensors). `model: {contributions: [...]}` (docs/configuration.md) runs one model per source and
hands the guard their sum. Each contribution, per axis it serves, is limited on its own
before the sum: its prediction clamped to its `max_abs_um`, moved no faster than its
`max_slew_um_per_s`, and when one of its inputs goes bad it follows its own fault policy
(`hold` its last value, `ramp_to_zero` at the guard's ramp rate, or `disable`: the axis
faults and its own policy applies) while the other contributions go on compensating; back
to normal once its inputs have been good for the guard's `recovery_s`, slewing from where it
stands. The axis guard still clamps and slews the sum. A contribution that has had no good
input vector yet contributes 0 (under `disable`: the axis waits for it).

The per-contribution values (`part_um`, what each adds; `part_raw_um`, its model's own
prediction) and states are read by the status record, the data log (`pred_<axis>_<name>_um`)
and the replay report.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from compd.core.config import Strict
from compd.models.base import Model, ModelStage

STARTING, NORMAL, FAULT, RECOVERING = 0, 1, 2, 3
POLICIES = ("hold", "ramp_to_zero", "disable")
Policy = Literal["hold", "ramp_to_zero", "disable"]


class ContributionParams(Strict):
    """One contribution as the config resolved it: its model (kind, wiring, params as in its
    file) and its limits per output axis (its own, or its axis's)."""

    name: str
    kind: str
    inputs: list[str]
    outputs: list[str]
    params: dict[str, Any]
    fit: dict[str, Any] = Field(default_factory=dict)
    file: str | None = None
    update_period_s: float | None = None
    max_abs_um: list[float]
    max_slew_um_per_s: list[float]
    fault_policy: list[Policy]


class ContributionSetParams(Strict):
    """The contributions and what their fault policies share with the guard."""

    contributions: list[ContributionParams]
    ramp_um_per_s: float = 1.0
    recovery_s: float = 5.0


class _Part:
    """One contribution's model and its per-axis limiter state (arrays made once)."""

    def __init__(self, p: ContributionParams, model: Model, idx: np.ndarray, axes: list[int]) -> None:
        self.name = p.name
        self.model = model
        self.idx = idx  # its inputs' places in the sum's inputs
        self.axes = axes  # its outputs' places in the sum's outputs
        self.x = np.zeros(len(idx))
        self.good = np.ones(len(idx), dtype=bool)
        self.raw = np.full(len(axes), math.nan)
        self.clamp = [float(v) for v in p.max_abs_um]
        self.slew = [float(v) for v in p.max_slew_um_per_s]
        self.policy = [POLICIES.index(v) for v in p.fault_policy]
        self.stage = ModelStage(model)  # its own start, update period and degraded mode


class Contributions(Model):
    """The sum of several contributions per axis (see the module)."""

    kind: ClassVar[str] = "contributions"
    Params: ClassVar[type[Strict]] = ContributionSetParams

    def __init__(
        self,
        params: Strict,
        inputs: list[str],
        outputs: list[str],
        fit: dict[str, Any] | None = None,
    ) -> None:
        from compd.models import MODELS

        assert isinstance(params, ContributionSetParams)
        super().__init__(params, inputs, outputs, fit)
        self.set_params = params
        self._parts: list[_Part] = []
        names: list[tuple[str, str]] = []
        for p in params.contributions:
            cls = MODELS.get(p.kind)
            model = cls(cls.Params.model_validate(p.params), list(p.inputs), list(p.outputs), dict(p.fit))
            model.file = p.file
            if p.update_period_s is not None:
                model.update_period_s = p.update_period_s
            idx = np.array([self.inputs.index(n) for n in p.inputs], dtype=np.intp)
            self._parts.append(_Part(p, model, idx, [self.outputs.index(a) for a in p.outputs]))
            names += [(p.name, a) for a in p.outputs]
        self.part_names = tuple(names)  # (contribution, axis) per part, in order
        n = len(names)
        self.part_um = np.zeros(n)  # what each part adds to its axis (after its own limits)
        self.part_raw_um = np.full(n, math.nan)  # its model's own prediction
        self.part_state = np.full(n, STARTING, dtype=np.uint8)
        self.part_clamped = np.zeros(n, dtype=bool)
        self._value = [0.0] * n
        self._state = [STARTING] * n
        self._clamped = [False] * n
        self._good_since = [math.nan] * n
        self._ramp = float(params.ramp_um_per_s)
        self._recovery_s = float(params.recovery_s)
        self._last_t = math.nan
        held = self._held_out()
        if held:
            self.fit_info["held_out_rmse_um"] = held

    @property
    def models(self) -> list[tuple[str, Model]]:
        """Each contribution's name and model, in order."""
        return [(p.name, p.model) for p in self._parts]

    def _held_out(self) -> dict[str, float]:
        """Per axis, when every contribution on it has a held-out figure: their root sum of
        squares (the probe adapter's σ of the model's own error; an upper bound)."""
        out: dict[str, float] = {}
        for axis in self.outputs:
            sq = 0.0
            for p in self._parts:
                if axis not in p.model.outputs:
                    continue
                figs = p.model.fit_info.get("held_out_rmse_um")
                v = figs.get(axis) if isinstance(figs, dict) else None
                if not isinstance(v, int | float) or isinstance(v, bool) or not 0 <= v < 1e4:
                    break
                sq += float(v) ** 2
            else:
                out[axis] = math.sqrt(sq)
        return out

    @property
    def supports_degraded(self) -> bool:
        return True  # a contribution with a bad input steps aside; the others go on

    @property
    def starts_by_parts(self) -> bool:
        return True  # each contribution starts on its own first good inputs

    def start(self, x: np.ndarray, t_s: float) -> None:
        """Nothing to capture for the sum: each contribution starts on its own first good inputs."""

    def run(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        self._step(x, None, t_s, out)

    def run_degraded(self, x: np.ndarray, good: np.ndarray, t_s: float, out: np.ndarray) -> None:
        self._step(x, good, t_s, out)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        self._step(x, None, t_s, out)

    def evaluate_degraded(self, x: np.ndarray, good: np.ndarray, t_s: float, out: np.ndarray) -> None:
        self._step(x, good, t_s, out)

    def _step(self, x: np.ndarray, good: np.ndarray | None, t_s: float, out: np.ndarray) -> None:
        """Every contribution evaluated on its inputs (those due), limited, and summed into `out`."""
        last = self._last_t
        dt = t_s - last if last == last else 0.0
        if dt < 0.0:
            dt = 0.0
        self._last_t = t_s
        out.fill(0.0)
        k = 0
        for part in self._parts:
            ok = True
            np.take(x, part.idx, out=part.x)
            if good is not None:
                np.take(good, part.idx, out=part.good)
                ok = bool(part.good.all())
            if t_s >= part.stage.next_s and part.stage.step(part.x, part.good, ok, t_s, part.raw):
                self.state_dirty = True  # its T0 and memory are worth keeping now
            for j, a in enumerate(part.axes):
                v = self._limit(k, part, j, float(part.raw[j]), t_s, dt)
                self.part_raw_um[k] = part.raw[j]
                self.part_um[k] = v
                self.part_state[k] = self._state[k]
                out[a] += v
                k += 1

    def _limit(self, k: int, part: _Part, j: int, raw: float, t_s: float, dt: float) -> float:
        """Part k's value this step: its clamp, slew and fault policy (the guard's rules, per part)."""
        st = self._state[k]
        value = self._value[k]
        pol = part.policy[j]
        finite = raw == raw and raw not in (math.inf, -math.inf)
        if finite:
            lim = part.clamp[j]
            target = raw
            if raw > lim or raw < -lim:
                target = lim if raw > 0 else -lim
                if not self._clamped[k]:
                    self._clamp_event(k, t_s, raw, lim, True)
            elif self._clamped[k]:
                self._clamp_event(k, t_s, raw, lim, False)
            if st == FAULT:
                st = RECOVERING
                self._good_since[k] = t_s
                self._event(t_s, k, "recovering", "inputs good")
            if st == RECOVERING and t_s - self._good_since[k] >= self._recovery_s:
                st = NORMAL
                self._event(t_s, k, "normal", "recovered")
            if st == STARTING:
                st = NORMAL
            if st == NORMAL:
                step = part.slew[j] * dt
                d = target - value
                value = value + (step if d > step else (-step if d < -step else d))
        elif st in (NORMAL, RECOVERING):
            if st == NORMAL:
                self._event(t_s, k, "fault", "input bad")
            st = FAULT
        elif st == STARTING:
            self._state[k] = st
            return math.nan if pol == 2 else 0.0
        if st != NORMAL:  # FAULT or RECOVERING: the part's policy
            if pol == 1:
                step = self._ramp * dt
                value = value - step if value > step else (value + step if value < -step else 0.0)
            elif pol == 2:
                value = 0.0
                self._state[k] = st
                self._value[k] = value
                return math.nan
        self._state[k] = st
        self._value[k] = value
        return value

    def _subject(self, k: int) -> str:
        name, axis = self.part_names[k]
        return f"{axis}/{name}"

    def _event(self, t_s: float, k: int, event: str, reason: str) -> None:
        if self.emit is not None:
            self.emit(t_s, self._subject(k), event, reason)

    def _clamp_event(self, k: int, t_s: float, raw: float, lim: float, on: bool) -> None:
        self._clamped[k] = on
        self.part_clamped[k] = on
        if on:
            self._event(t_s, k, "clamped", f"the contribution predicts {raw:.1f} um, beyond its clamp of {lim:g} um")
        else:
            self._event(t_s, k, "unclamped", f"the contribution is inside its clamp of {lim:g} um")

    def predict(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """The sum as the loop steps it (each contribution limited), over a log from a cold start."""
        fresh = type(self)(self.params, self.inputs, self.outputs, self.fit_info)
        return Model.predict_rows(fresh, np.asarray(X, dtype=float), t_s)

    def get_state(self) -> dict[str, Any]:
        return {p.name: p.model.get_state() for p in self._parts}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        for p in self._parts:
            own = state.get(p.name)
            if isinstance(own, dict):
                p.model.set_state(own, elapsed_s)

    def to_dict(self) -> dict[str, Any]:
        """The contributions, each as its model file plus its name and limits."""
        out = []
        for cp, p in zip(self.set_params.contributions, self._parts, strict=True):
            d = p.model.to_dict()
            d.update(name=cp.name, file=cp.file, max_abs_um=cp.max_abs_um, max_slew_um_per_s=cp.max_slew_um_per_s,
                     fault_policy=cp.fault_policy)
            out.append(d)
        return {"kind": self.kind, "inputs": self.inputs, "outputs": self.outputs, "contributions": out}

    def coefficients(self) -> dict[str, Any]:
        return {p.name: p.model.coefficients() for p in self._parts}

    def get_status(self) -> dict[str, Any]:
        """The sum's wiring, and each contribution's own status with its name and limits."""
        parts = []
        for cp, p in zip(self.set_params.contributions, self._parts, strict=True):
            s = p.model.get_status()
            s.update(name=cp.name, limits={a: {"max_abs_um": cp.max_abs_um[j],
                                               "max_slew_um_per_s": cp.max_slew_um_per_s[j],
                                               "fault_policy": cp.fault_policy[j]} for j, a in enumerate(cp.outputs)})
            parts.append(s)
        return {"kind": self.kind, "inputs": self.inputs, "outputs": self.outputs, "file": None, "fit": {},
                "coefficients": {}, "state": self.get_state(), "contributions": parts}

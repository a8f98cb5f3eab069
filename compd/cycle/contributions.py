"""The stage that sums contributions per axis, each a model on its own inputs with its own clamp, slew and fault policy.

A machine's axis has several heat sources: a vertical machining centre's Z grows with the
spindle (its own model on its own sensor) and with the column (a structure model on column
sensors). `model: {contributions: [...]}` (docs/configuration.md) runs one model per source and
hands the guard their sum. Each contribution, per axis it serves, is limited on its own
before the sum: its prediction clamped to its `max_abs_um`, moved no faster than its
`max_slew_um_per_s`, and when one of its inputs goes bad it follows its own fault policy
(`hold` its last value, `ramp_to_zero` at the guard's ramp rate, or `disable`: the axis
faults and its own policy applies) while the other contributions go on compensating; back
to normal once its inputs have been good for the guard's `recovery_s`, slewing from where it
stands. Each contribution on each of its axes is a channel of one limiter (compd.cycle.limiter),
the guard's: the same clamp, slew and policies, the same states. The axis guard still clamps and
slews the sum. A contribution that has had no good input vector yet contributes 0 (under
`disable`: the axis waits for it).

A sum of contributions is a `Model` for the loop (the model stage runs it), but it is a stage of
the cycle: its params (`ContributionSetParams`, compd.core.config) are what compd.config resolves
`model.contributions` or a model file of kind `contributions` to, and compd.cycle.pipeline's
`build_model` builds it from them (compd.config sits below the cycle and never names this class).

The per-contribution values (`part_um`, what each adds; `part_raw_um`, its model's own
prediction) and states are read by the status record, the data log (`pred_<axis>_<name>_um`)
and the replay report.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from compd.core.config import SUM_KIND, ContributionParams, ContributionSetParams, Strict
from compd.cycle.limiter import (
    CLAMPED,
    NORMAL,
    TO_FAULT,
    TO_NORMAL,
    TO_RECOVERING,
    UNCLAMPED,
    Limiter,
    Policy,
)
from compd.models import MODELS
from compd.models.base import Model, ModelStage


class _Part:
    """One contribution's model, where its inputs and outputs sit in the sum's, and its buffers (made once)."""

    def __init__(self, p: ContributionParams, model: Model, idx: np.ndarray, axes: list[int]) -> None:
        self.name = p.name
        self.model = model
        self.idx = idx  # its inputs' places in the sum's inputs
        self.axes = axes  # its outputs' places in the sum's outputs
        self.x = np.zeros(len(idx))
        self.good = np.ones(len(idx), dtype=bool)
        self.raw = np.full(len(axes), math.nan)
        self.stage = ModelStage(model)  # its own start, update period and degraded mode


class Contributions(Model):
    """The sum of several contributions per axis (see the module)."""

    kind: ClassVar[str] = SUM_KIND
    Params: ClassVar[type[Strict]] = ContributionSetParams

    def __init__(
        self,
        params: Strict,
        inputs: list[str],
        outputs: list[str],
        fit: dict[str, Any] | None = None,
    ) -> None:
        assert isinstance(params, ContributionSetParams)
        super().__init__(params, inputs, outputs, fit)
        self.set_params = params
        self._parts: list[_Part] = []
        names: list[tuple[str, str]] = []
        clamps: list[float] = []
        slews: list[float] = []
        policies: list[Policy] = []
        for p in params.contributions:
            cls = MODELS.get(p.kind)
            model = cls(cls.Params.model_validate(p.params), list(p.inputs), list(p.outputs), dict(p.fit))
            model.file = p.file
            if p.update_period_s is not None:
                model.update_period_s = p.update_period_s
            idx = np.array([self.inputs.index(n) for n in p.inputs], dtype=np.intp)
            self._parts.append(_Part(p, model, idx, [self.outputs.index(a) for a in p.outputs]))
            names += [(p.name, a) for a in p.outputs]
            clamps += p.max_abs_um
            slews += p.max_slew_um_per_s
            policies += [Policy.named(v) for v in p.fault_policy]
        self.part_names = tuple(names)  # (contribution, axis) per part, in order
        n = len(names)
        # each part a channel of the limiter: its clamp, slew, policy, state
        self.limiter = Limiter(clamps, slews, policies, params.ramp_um_per_s, params.recovery_s)
        self._disables = [p is Policy.DISABLE for p in policies]  # a part under `disable` faults its axis
        self.part_um = np.zeros(n)  # what each part adds to its axis (after its own limits)
        self.part_raw_um = np.full(n, math.nan)  # its model's own prediction
        self.part_state = self.limiter.state
        self.part_clamped = self.limiter.clamped
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
                v = self._limit(k, float(part.raw[j]), t_s, dt)
                self.part_raw_um[k] = part.raw[j]
                self.part_um[k] = v
                out[a] += v
                k += 1

    def _limit(self, k: int, raw: float, t_s: float, dt: float) -> float:
        """Part k's value this step: the limiter's (its clamp, slew and fault policy), NaN while
        a part under `disable` is not normal (its axis then faults: the axis's own policy)."""
        lim = self.limiter
        said = lim.step(k, raw, dt, t_s)
        if said:
            if said & (CLAMPED | UNCLAMPED):
                self._clamp_event(k, t_s, raw, lim.max_abs_um[k], bool(said & CLAMPED))
            if said & TO_RECOVERING:
                self._event(t_s, k, "recovering", "inputs good")
            if said & TO_NORMAL:
                self._event(t_s, k, "normal", "recovered")
            if said & TO_FAULT:
                self._event(t_s, k, "fault", "input bad")
        if self._disables[k] and lim.state[k] != NORMAL:
            return math.nan
        return float(lim.value_um[k])

    def _subject(self, k: int) -> str:
        name, axis = self.part_names[k]
        return f"{axis}/{name}"

    def _event(self, t_s: float, k: int, event: str, reason: str) -> None:
        if self.emit is not None:
            self.emit(t_s, self._subject(k), event, reason)

    def _clamp_event(self, k: int, t_s: float, raw: float, lim: float, on: bool) -> None:
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
            d.update(
                name=cp.name,
                file=cp.file,
                max_abs_um=cp.max_abs_um,
                max_slew_um_per_s=cp.max_slew_um_per_s,
                fault_policy=cp.fault_policy,
            )
            out.append(d)
        return {"kind": self.kind, "inputs": self.inputs, "outputs": self.outputs, "contributions": out}

    def coefficients(self) -> dict[str, Any]:
        return {p.name: p.model.coefficients() for p in self._parts}

    def get_status(self) -> dict[str, Any]:
        """The sum's wiring, and each contribution's own status with its name and limits."""
        parts = []
        for cp, p in zip(self.set_params.contributions, self._parts, strict=True):
            s = p.model.get_status()
            s.update(
                name=cp.name,
                limits={
                    a: {
                        "max_abs_um": cp.max_abs_um[j],
                        "max_slew_um_per_s": cp.max_slew_um_per_s[j],
                        "fault_policy": cp.fault_policy[j],
                    }
                    for j, a in enumerate(cp.outputs)
                },
            )
            parts.append(s)
        return {
            "kind": self.kind,
            "inputs": self.inputs,
            "outputs": self.outputs,
            "file": None,
            "fit": {},
            "coefficients": {},
            "state": self.get_state(),
            "contributions": parts,
        }

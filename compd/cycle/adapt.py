"""Probe-updated compensation: a Kalman filter per axis on the model's drifting offset (and gain).

A probe measurement (plant time, axis, measured thermal error µm, σ) says how far the
machine's true error is from what the model predicts. Per axis the adapter keeps the
state s = (b, g): an offset b (µm) and, optionally, a gain error g on the model's
prediction p, so that the error the loop compensates is

    ê = p + b + g p

Both drift as random walks: between probes the covariance grows by Q Δt, with
Q = diag(q_b², q_g²) per hour (`offset_drift_um_per_sqrt_h`, `gain_drift_per_sqrt_h`).
On an axis whose error depends on where it stands (a feed axis), `slope_position` adds a
slope m over the position y (m from `slope_ref_mm`): ê = p + b + g p + m y, H = (1, p, y).
A probe z at prediction p is the measurement z = p + H s + v, H = (1, p), v ~ N(0, σ²):

    ν = z − (p + H s),  S = H P Hᵀ + σ² + σ_m²
    |ν| > k √S      → rejected (innovation gate, `gate_sigma` k): logged, never applied
    K = P Hᵀ / S,  s ← s + K ν,  P ← (I − K H) P (I − K H)ᵀ + K (σ² + σ_m²) Kᵀ   (Joseph form)

σ_m is the model's own error at the probe (`model_sigma_um`, by default the held-out RMSE of
its fit): a model that is right on average is still off by that much at any moment, and one
probe cannot tell that from an offset, so it moves the estimate only as far as it outweighs
it; before the first probe the offset's own σ is σ_m too (`initial_offset_sigma_um`): a model
fitted on a day is not off by more on the next. Probes never hurt: what reaches the prediction
is each estimated term only as far as it stands out from its own uncertainty where the axis is:
c·max(0, 1 − k² var(c)/c²), c = H s and var(c) = H P Hᵀ for this cycle's H (`apply_above_sigma`
k): where the evidence does not say the model is off by more than the noise, the model runs as
fitted.

An update changes ê at once, but the correction still reaches the machine through the
guard, whose slew limit moves it, never steps it. An estimate without a probe for
`stale_after_s` holds (`stale_policy: hold`) or decays to zero with `decay_tau_s`
(`decay`); `reject_fault_after` probes rejected in a row raise a fault event (the
model or the probe is wrong, and the operator should know). With `apply: false` the
estimate is kept, logged and shown but not applied (observe).

Nothing a probe carries is trusted before its numbers are checked (`probe_problem`, here,
where every probe passes: the command line, the socket, a CNC's probe block, a replayed
log): the error finite and within ±`MAX_PROBE_ERROR_UM`, σ within [`MIN_PROBE_SIGMA_UM`,
`MAX_PROBE_SIGMA_UM`], the position finite and within ±`MAX_PROBE_POSITION_MM`; a probe
outside is rejected with its reason. An update whose s or P would not be finite is
rejected too and the estimate stays as it was; and a saved state is taken only when every
number is finite and P a covariance (`state_problem`), so a bad probe can never poison the
estimate, the state file or the next start.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from compd.core.config import AdaptConfig
from compd.core.errors import BadInput
from compd.core.probe import Probe, brief, finite_number, probe_problem

OFFSET_PRIOR_UM = 5.0  # σ of the offset before the first probe when the model's own error is not known
PSD_TOLERANCE = 1e-9  # of P's largest entry: how far P may be from symmetric or have a negative eigenvalue
PRIOR_PROBES = 2.0  # the fit's held-out σ_m counts as this many probes' worth of scatter
HISTORY = 4096  # cycles of (position, prediction, correction sent) kept per slope axis (8 s at 2 ms)
POSITION_MATCH_MM = 0.5  # the axis stood "at" the probe's position within this


def state_problem(state: Any, n: int | None = None) -> str | None:
    """Why an axis's saved estimate (`AxisEstimate.get_state`) cannot be taken, or None: `s` of `n`
    finite numbers (None: any length), `P` an n × n covariance (finite, symmetric and positive
    semi-definite within PSD_TOLERANCE of its largest entry), the counts whole numbers ≥ 0 and
    the times finite or null."""
    if not isinstance(state, dict):
        return f"not a mapping: {brief(state)}"
    s, P = state.get("s"), state.get("P")
    if not isinstance(s, list) or not s:
        return f"s is not a list of numbers: {brief(s)}"
    n = len(s) if n is None else n
    if len(s) != n:
        return f"s has {len(s)} terms, the estimate {n} (adapt.gain or adapt.slope_position changed)"
    if not isinstance(P, list) or len(P) != n or not all(isinstance(row, list) and len(row) == n for row in P):
        return f"P is not {n} × {n}"
    for name, values in (("s", s), *((f"P[{i}]", row) for i, row in enumerate(P))):
        bad = [v for v in values if not finite_number(v)]
        if bad:
            return f"{name} holds {brief(bad[0])}, not a finite number"
    for key in ("accepted", "rejected"):
        v = state.get(key, 0)
        if not finite_number(v) or v < 0 or v != int(v):
            return f"{key} is {brief(v)}, not a count"
    for key in ("t_probe_s", "probe_age_s"):
        v = state.get(key)
        if v is not None and not finite_number(v):
            return f"{key} is {brief(v)}, not a finite number or null"
    cov = np.asarray(P, float)
    tol = PSD_TOLERANCE * max(1.0, float(np.abs(cov).max()))
    if float(np.abs(cov - cov.T).max()) > tol:
        return "P is not symmetric"
    low = float(np.linalg.eigvalsh(cov).min())
    if low < -tol:
        return f"P is not positive semi-definite (an eigenvalue {low:g})"
    return None


class AxisEstimate:
    """The Kalman filter of one axis: state (b, g) or (b,) and its covariance."""

    def __init__(
        self, cfg: AdaptConfig, slope: bool = False, model_sigma_um: float = 0.0, learn_sigma: bool = False
    ) -> None:
        self.cfg = cfg
        self.model_var_um2 = model_sigma_um * model_sigma_um
        # σ_m learnt from the probes themselves: how much the model's miss changes from one probe to the
        # next beyond the probes' σ and the offset's drift (an offset that stays cancels in the change,
        # a miss that comes and goes does not), with the fit's figure as a prior worth PRIOR_PROBES
        self.learn_sigma = learn_sigma
        self._prior_var_um2 = self.model_var_um2
        # the offset before any probe: a fitted model is off on a new day by about its own error (σ_m),
        # not by more; without a figure for σ_m, OFFSET_PRIOR_UM
        self.initial_offset_sigma_um = (
            cfg.initial_offset_sigma_um
            if cfg.initial_offset_sigma_um is not None
            else model_sigma_um
            if model_sigma_um > 0.0
            else OFFSET_PRIOR_UM
        )
        self._last_miss: tuple[float, float, float] | None = None  # (t, miss z − p, probe σ²)
        self._change_sum_um2 = 0.0
        self._change_n = 0
        self.i_gain = 1 if cfg.gain else -1
        self.i_slope = (2 if cfg.gain else 1) if slope else -1
        self.n = 1 + cfg.gain + slope
        self.s = np.zeros(self.n)
        self.P = np.zeros((self.n, self.n))
        self.reset()
        self.t_s: float | None = None  # time of the state (last predict step)
        self.t_probe_s: float | None = None
        self.accepted = 0
        self.rejected = 0
        self.rejected_in_a_row = 0
        self.last_innovation_um = math.nan

    def reset(self) -> None:
        """Forget: zero offset and gain with the initial uncertainty (a new model)."""
        self.s[:] = 0.0
        self.P[:] = 0.0
        self.P[0, 0] = self.initial_offset_sigma_um**2
        if self.i_gain > 0:
            self.P[self.i_gain, self.i_gain] = self.cfg.initial_gain_sigma**2
        if self.i_slope > 0:
            self.P[self.i_slope, self.i_slope] = self.cfg.initial_slope_sigma_um_per_m**2

    def advance(self, t_s: float) -> None:
        """Let the covariance grow (random walk) and a stale estimate decay, up to t_s."""
        if self.t_s is None:
            self.t_s = t_s
            return
        dt = t_s - self.t_s
        if dt <= 0:
            return
        self.t_s = t_s
        self._grow(dt / 3600.0)
        cfg = self.cfg
        if cfg.stale_policy == "decay" and self.t_probe_s is not None and t_s - self.t_probe_s > cfg.stale_after_s:
            self.s *= math.exp(-dt / cfg.decay_tau_s)

    def _grow(self, h: float) -> None:
        """The random walk's covariance over h hours."""
        self.P[0, 0] += self.cfg.offset_drift_um_per_sqrt_h**2 * h
        if self.i_gain > 0:
            self.P[self.i_gain, self.i_gain] += self.cfg.gain_drift_per_sqrt_h**2 * h
        if self.i_slope > 0:
            self.P[self.i_slope, self.i_slope] += self.cfg.slope_drift_um_per_m_sqrt_h**2 * h

    def correction_um(self, pred_um: float, pos_m: float = 0.0) -> float:
        """What the estimate adds to the model's prediction at position y (m): c = b + g p + m y
        only as far as it stands out from its own uncertainty there, c·max(0, 1 − k² var(c)/c²)
        with var(c) = H P Hᵀ, H = (1, p, y) (`apply_above_sigma` k; 0 applies c as estimated)."""
        s, P = self.s, self.P
        h1 = pred_um if self.i_gain > 0 else 0.0
        h2 = pos_m if self.i_slope > 0 else 0.0
        c = float(s[0])
        var = float(P[0, 0])
        if self.i_gain > 0:
            g = self.i_gain
            c += float(s[g]) * h1
            var += h1 * h1 * float(P[g, g]) + 2.0 * h1 * float(P[0, g])
        if self.i_slope > 0:
            m = self.i_slope
            c += float(s[m]) * h2
            var += h2 * h2 * float(P[m, m]) + 2.0 * h2 * float(P[0, m])
            if self.i_gain > 0:
                var += 2.0 * h1 * h2 * float(P[self.i_gain, m])
        k = self.cfg.apply_above_sigma
        if k <= 0.0 or c == 0.0:
            return c
        shrink = 1.0 - k * k * max(var, 0.0) / (c * c)
        return c * shrink if shrink > 0.0 else 0.0

    def update(
        self, pred_um: float, z_um: float, sigma_um: float, t_s: float, pos_m: float = 0.0
    ) -> tuple[bool, float, float, str | None]:
        """One probe: (accepted, innovation µm, its σ µm, why it was rejected or None). An update
        whose s or P would not be finite is rejected and leaves the estimate as it was."""
        self.advance(t_s)
        H = np.zeros(self.n)
        H[0] = 1.0
        if self.i_gain > 0:
            H[self.i_gain] = pred_um
        if self.i_slope > 0:
            H[self.i_slope] = pos_m
        with np.errstate(all="ignore"):  # numpy's own overflow warnings: what is not finite is rejected below
            nu = z_um - (pred_um + float(H @ self.s))
            r = sigma_um * sigma_um + self.model_var_um2  # the probe's noise and the model's own error now
            S = float(H @ self.P @ H) + r
            sd = math.sqrt(S) if S >= 0.0 else math.nan
            self.last_innovation_um = nu
            why = None
            if not (math.isfinite(S) and S > 0.0):
                why = f"the innovation's variance is {S:g}, not a positive finite number"
            elif not math.isfinite(nu):
                why = "the innovation is not a finite number"
            elif abs(nu) > self.cfg.gate_sigma * sd:
                why = f"innovation {nu:.2f} um beyond gate_sigma {self.cfg.gate_sigma:g} x {sd:.2f} um"
            else:
                K = (self.P @ H) / S
                s = self.s + K * nu
                A = np.eye(self.n) - np.outer(K, H)
                P = A @ self.P @ A.T + np.outer(K, K) * r
                if not (np.isfinite(s).all() and np.isfinite(P).all()):
                    why = "the update would make the estimate non-finite"
        if why is not None:
            self.rejected += 1
            self.rejected_in_a_row += 1
            return False, nu, sd, why
        self.s[:] = s
        self.P[:] = P
        if self.learn_sigma:  # from accepted probes only: an outlier teaches nothing
            self._learn_sigma(t_s, z_um - pred_um, sigma_um * sigma_um)
        self.accepted += 1
        self.rejected_in_a_row = 0
        self.t_probe_s = t_s
        return True, nu, sd, None

    def _learn_sigma(self, t_s: float, miss_um: float, probe_var_um2: float) -> None:
        """σ_m² from the change of the model's miss between consecutive probes: E[(Δmiss)²] =
        2 σ_m² + σ_k² + σ_(k−1)² + q Δt for misses of independent model error on a drifting offset."""
        last = self._last_miss
        self._last_miss = (t_s, miss_um, probe_var_um2)
        if last is None or miss_um != miss_um:
            return
        dt_h = max(t_s - last[0], 0.0) / 3600.0
        drift = self.cfg.offset_drift_um_per_sqrt_h**2 * dt_h
        change = miss_um - last[1]
        self._change_sum_um2 += 0.5 * (change * change - probe_var_um2 - last[2] - drift)
        self._change_n += 1
        learnt = (PRIOR_PROBES * self._prior_var_um2 + self._change_sum_um2) / (PRIOR_PROBES + self._change_n)
        self.model_var_um2 = max(self._prior_var_um2, learnt)

    def get_state(self) -> dict[str, Any]:
        age = None if self.t_probe_s is None or self.t_s is None else self.t_s - self.t_probe_s
        return {
            "s": [float(v) for v in self.s],
            "P": [[float(v) for v in row] for row in self.P],
            "t_probe_s": self.t_probe_s,
            "accepted": self.accepted,
            "rejected": self.rejected,
            "probe_age_s": age,
        }

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0, now_s: float | None = None) -> None:
        """Take a saved state (ValueError naming what is wrong with it: `state_problem`). From a
        file (`now_s`, the loop time now; `elapsed_s` since it was saved): the last probe's time
        moves onto this loop's clock and the covariance grows by the drift over the time the
        daemon was down."""
        why = state_problem(state, self.n)
        if why is not None:
            raise ValueError(why)
        self.s[:] = np.asarray(state["s"], float)
        self.P[:] = np.asarray(state["P"], float)
        self.t_probe_s = state.get("t_probe_s")
        self.accepted = int(state.get("accepted", 0))
        self.rejected = int(state.get("rejected", 0))
        if now_s is not None:
            age = state.get("probe_age_s")
            self.t_probe_s = None if age is None else now_s - float(age) - elapsed_s
            self.t_s = None
            self._grow(max(elapsed_s, 0.0) / 3600.0)


class Adapter:
    """Per-axis estimates on top of the model's outputs; the loop drains `inbox` every cycle.

    `inbox` is a deque: producers (a probe source's thread, the command line, a replay)
    append Probe objects, the cycle pops them, so it never waits on them.
    """

    def __init__(self, cfg: AdaptConfig, axes: list[str], model_sigma_um: dict[str, float] | None = None) -> None:
        """`model_sigma_um`: per axis the model's own error (its fit's held-out RMSE), used where
        the config's `model_sigma_um` is none."""
        self.cfg = cfg
        self.axes = list(axes)
        fitted = model_sigma_um or {}
        self.model_sigma_um = [
            cfg.model_sigma_um if cfg.model_sigma_um is not None else float(fitted.get(a, 0.0)) for a in axes
        ]
        learn = cfg.model_sigma_um is None
        self.est = [
            AxisEstimate(cfg, slope=a in cfg.slope_position, model_sigma_um=m, learn_sigma=learn)
            for a, m in zip(axes, self.model_sigma_um, strict=True)
        ]
        # per axis: the signal its slope term reads (the axis position, mm), or None
        self.position_signal = [cfg.slope_position.get(a) for a in axes]
        self.pos_m = np.zeros(len(axes))  # the positions of this cycle (m from slope_ref_mm)
        self._pos_idx: list[tuple[int, int]] = []
        # per slope axis, the last HISTORY cycles: loop time, position (mm) and the correction
        # sent; a residual probe's position finds what was applied where it was measured
        self._hist_pos_mm = np.full((len(axes), HISTORY), math.nan)
        self._hist_out_um = np.full((len(axes), HISTORY), math.nan)
        self._hist_pred_um = np.full((len(axes), HISTORY), math.nan)
        self._hist_i = 0
        self.inbox: deque[Probe] = deque(maxlen=1000)
        self.events: deque[dict[str, Any]] = deque(maxlen=1000)  # accepted/rejected probes, faults
        self.offset_um = np.zeros(len(axes))  # b + g p of the last cycle, per axis
        self.fault = [False] * len(axes)
        # the probes taken this cycle (whole error µm, position mm; NaN for none), for the data log
        self.probe_um = np.full(len(axes), math.nan)
        self.probe_pos_mm = np.full(len(axes), math.nan)
        self.probe_seq = 0  # probes taken so far: a change tells the log a row is due
        self._probed = False
        # called with get_state() after a probe changed the estimate (the state file's writer)
        self.on_state: Callable[[dict[str, Any]], None] | None = None

    def bind(self, signal_index: dict[str, int]) -> None:
        """Where each slope axis's position signal lives in the frame (name → index)."""
        self._pos_idx = []
        for a, name in enumerate(self.position_signal):
            if name is None:
                continue
            if name not in signal_index:
                raise BadInput(
                    f"{name!r} is not a signal of any source", path=("adapt", "slope_position", self.axes[a])
                )
            self._pos_idx.append((a, signal_index[name]))
        for axis in self.cfg.slope_position:
            if axis not in self.axes:
                raise BadInput(f"{axis!r} is not an output of the model", path=("adapt", "slope_position", axis))

    def read_positions(self, values: np.ndarray) -> None:
        """This cycle's positions of the slope axes from the frame's values (mm → m from slope_ref_mm)."""
        for a, i in self._pos_idx:
            v = float(values[i])
            if math.isfinite(v):
                self.pos_m[a] = (v - self.cfg.slope_ref_mm) / 1000.0

    def record(self, pred_um: np.ndarray, sent_um: np.ndarray) -> None:
        """After the guard: this cycle's positions of the slope axes, the model's prediction
        and the correction sent, into the last HISTORY cycles."""
        if not self._pos_idx:
            return
        i = self._hist_i
        for a, _ in self._pos_idx:
            self._hist_pos_mm[a, i] = self.pos_m[a] * 1000.0 + self.cfg.slope_ref_mm
            self._hist_pred_um[a, i] = pred_um[a]
            self._hist_out_um[a, i] = sent_um[a]
        self._hist_i = (i + 1) % HISTORY

    def at_position(self, a: int, position_mm: float) -> tuple[float, float] | None:
        """(prediction, correction sent) of the last of the HISTORY cycles in which axis `a`
        stood at `position_mm`, or None: not there lately, or no position signal."""
        if all(a != k for k, _ in self._pos_idx):
            return None
        order = (self._hist_i - 1 - np.arange(HISTORY)) % HISTORY  # newest first
        hit = np.flatnonzero(np.abs(self._hist_pos_mm[a, order] - position_mm) <= POSITION_MATCH_MM)
        if hit.size == 0:
            return None
        j = order[hit[0]]
        p, c = float(self._hist_pred_um[a, j]), float(self._hist_out_um[a, j])
        return (p, c) if math.isfinite(p) and math.isfinite(c) else None

    def reset(self) -> None:
        for e in self.est:
            e.reset()
            e.t_probe_s = None

    def apply(
        self,
        pred_um: np.ndarray,
        now_s: float,
        out_um: np.ndarray,
        applied_um: np.ndarray | None = None,
        terms: list[tuple[float, float]] | None = None,
    ) -> None:
        """out = pred + b + g pred per axis (pred if `apply` is off), after taking the inbox's probes.

        `applied_um`: the correction the machine applies now, per axis (for residual probes).
        `terms`: the model's linear terms (slope µm/mm, P0 mm per axis, `Model.linear_terms`) when
        its outputs are the error at P0 and the CNC applies the slope (Siemens tanβ): a probe at
        position y is then compared with pred + slope·(y − P0), the error the model predicts there."""
        if self._probed:
            self.probe_um.fill(math.nan)
            self.probe_pos_mm.fill(math.nan)
            self._probed = False
        while self.inbox:
            self._take(self.inbox.popleft(), pred_um, applied_um, terms)
        for a, e in enumerate(self.est):
            e.advance(now_s)
            p = float(pred_um[a])
            c = e.correction_um(p, float(self.pos_m[a])) if math.isfinite(p) else 0.0
            self.offset_um[a] = c
            out_um[a] = p + c if self.cfg.apply else p

    def _take(
        self,
        probe: Probe,
        pred_um: np.ndarray,
        applied_um: np.ndarray | None,
        terms: list[tuple[float, float]] | None = None,
    ) -> None:
        if probe.axis not in self.axes:
            self.events.append({"t_s": probe.t_s, "axis": probe.axis, "event": "unknown_axis", "source": probe.source})
            return
        a = self.axes.index(probe.axis)
        e = self.est[a]
        position = probe.position_mm
        if isinstance(position, float) and math.isnan(position):  # no position (a log row without one)
            position = None
        bad = probe_problem(probe.error_um, probe.sigma_um, position)
        if bad is not None:  # numbers no probe measures: rejected, the estimate untouched
            e.rejected += 1
            e.rejected_in_a_row += 1
            self._verdict(a, probe, False, probe.error_um, math.nan, math.nan, f"{bad[0]} {bad[1]}")
            return
        z = probe.error_um
        p = float(pred_um[a])
        # an axis that moves may have left the probe's position before the result came: the
        # prediction and the correction are those of the last cycle it stood there
        then = None
        if position is not None:
            then = self.at_position(a, position)
        if then is not None:
            p = then[0]
        # a model whose output is the error at P0 with a slope the CNC applies (Siemens tanβ):
        # at the probe's position it predicts p + slope·(y − P0), and the CNC applied c − that
        shift = 0.0
        if terms is not None and a < len(terms) and position is not None:
            slope_um_per_mm, p0_mm = terms[a]
            shift = slope_um_per_mm * (position - p0_mm)
        p += shift
        if probe.residual:  # deviation with the correction in place: the whole error is d − c
            c = then[1] if then is not None else None
            if c is None and applied_um is not None and math.isfinite(float(applied_um[a])):
                c = float(applied_um[a])
            if c is None:
                self.events.append(
                    {"t_s": probe.t_s, "axis": probe.axis, "event": "no_correction_known", "source": probe.source}
                )
                return
            z = probe.error_um - (c - shift)
        if not math.isfinite(p):  # no prediction to compare with: the probe cannot be used
            self.events.append(
                {
                    "t_s": probe.t_s,
                    "axis": probe.axis,
                    "event": "no_prediction",
                    "error_um": probe.error_um,
                    "source": probe.source,
                }
            )
            return
        sigma = probe.sigma_um if probe.sigma_um is not None else self.cfg.sigma_um
        pos_m = float(self.pos_m[a])  # where the axis stands now, unless the probe says where it measured
        if position is not None:
            pos_m = (position - self.cfg.slope_ref_mm) / 1000.0
        ok, nu, sd, why = e.update(p, z, sigma, probe.t_s, pos_m)
        self.probe_um[a] = z
        self.probe_pos_mm[a] = math.nan if position is None else position
        self.probe_seq += 1
        self._probed = True
        self._verdict(a, probe, ok, z, nu, sd, why)

    def _verdict(self, a: int, probe: Probe, ok: bool, z: float, nu: float, sd: float, why: str | None) -> None:
        """The event of a probe taken (accepted, or rejected with `why`), a fault after too many
        rejected in a row, and the state handed on."""
        e = self.est[a]
        ev = {
            "t_s": probe.t_s,
            "axis": probe.axis,
            "event": "accepted" if ok else "rejected",
            "error_um": z,
            "measured_um": probe.error_um,
            "innovation_um": nu,
            "innovation_sigma_um": sd,
            "offset_um": float(e.s[0]),
            "source": probe.source,
        }
        if why is not None:
            ev["reason"] = why
        self.events.append(ev)
        was = self.fault[a]
        self.fault[a] = e.rejected_in_a_row >= self.cfg.reject_fault_after
        if self.fault[a] and not was:
            self.events.append(
                {
                    "t_s": probe.t_s,
                    "axis": probe.axis,
                    "event": "fault",
                    "why": f"{e.rejected_in_a_row} probes rejected in a row",
                }
            )
        if self.on_state is not None:
            self.on_state(self.get_state())

    def get_state(self) -> dict[str, Any]:
        return {axis: e.get_state() for axis, e in zip(self.axes, self.est, strict=True)}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0, now_s: float | None = None) -> None:
        """Take a saved state (`get_state`), per axis it holds; nothing of it when any axis's part is
        bad: ValueError naming the axis and why (the caller starts the estimate fresh)."""
        for axis, e in zip(self.axes, self.est, strict=True):
            if axis in state and (why := state_problem(state[axis], e.n)) is not None:
                raise ValueError(f"{axis}: {why}")
        for axis, e in zip(self.axes, self.est, strict=True):
            if axis in state:
                e.set_state(state[axis], elapsed_s, now_s)

    def get_status(self) -> dict[str, Any]:
        out = {}
        for axis, e in zip(self.axes, self.est, strict=True):
            out[axis] = {
                "offset_um": float(e.s[0]),
                "offset_sigma_um": math.sqrt(max(e.P[0, 0], 0.0)),
                "model_sigma_um": math.sqrt(e.model_var_um2),
                "gain": float(e.s[e.i_gain]) if e.i_gain > 0 else None,
                "slope_um_per_m": float(e.s[e.i_slope]) if e.i_slope > 0 else None,
                "accepted": e.accepted,
                "rejected": e.rejected,
                "last_probe_s": e.t_probe_s,
                "applied": self.cfg.apply,
                "fault": self.fault[self.axes.index(axis)],
            }
        return out

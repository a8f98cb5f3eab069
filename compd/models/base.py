"""The model interface: declared inputs and outputs, params, per-cycle evaluation, state (fits: compd.identify)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import ConfigDict, Field, model_validator

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.models.lead import InputLead


class ModelParams(Strict):
    """Base of every model's params: every number finite (a NaN or infinite coefficient
    would make every prediction NaN), each inside the range its docstring states."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# Physical bounds shared by the kinds (units in the names; the models' docstrings).
TEMP_MIN_C, TEMP_MAX_C = -40.0, 150.0  # a reading on a machine tool (the guard's default limits)
MAX_RISE_K = 200.0  # a temperature rise from the reference
MAX_GAIN_UM_PER_K = 1e4  # α ≤ 1e-3 /K times a structure ≤ 10 m: µm of error per K
MAX_ERROR_UM = 1e4  # 10 mm: no thermal error of a machine tool comes near
MAX_LENGTH_MM = 1e5  # 100 m: longer than any machine axis or spindle
MAX_SPEED_RPM = 2e5  # faster than any machine spindle
MAX_LEAD_S = 3600.0  # a sensor that lags its structure by more than an hour measures something else


LeadS = Annotated[float, Field(ge=0, le=MAX_LEAD_S)]


class LeadParams(ModelParams):
    """What every kind's params share: the lead that compensates each input's sensor lag
    (compd.models.lead; compd's form, beyond the papers). Lists in input order; 0 = not led."""

    lead_s: list[LeadS] | None = Field(
        None, description="τ per input: the sensor's lag the lead undoes (0 = none; ≤ 3600 s)"
    )
    lead_filter_s: list[LeadS] | None = Field(
        None, description="τ_f per input: the low-pass the lead's derivative is taken through (> 0 where led)"
    )

    @model_validator(mode="after")
    def _lead(self) -> LeadParams:
        lead, filt = self.lead_s, self.lead_filter_s
        if (lead is None) != (filt is None):
            raise ValueError("lead_s and lead_filter_s go together (one value per input each)")
        if lead is not None and filt is not None:
            if len(lead) != len(filt):
                raise ValueError(f"lead_s has {len(lead)} values, lead_filter_s {len(filt)}: one per input each")
            for i, (a, b) in enumerate(zip(lead, filt, strict=True)):
                if a > 0 and not b > 0:
                    raise ValueError(f"lead_filter_s[{i}] must be > 0 where lead_s[{i}] leads the input")
        return self


def check_length(values: list[Any], n: int, key: str, what: str) -> None:
    """BadInput at params.<key> unless `values` has `n` entries (one per `what`)."""
    if len(values) != n:
        raise BadInput(f"has {len(values)} values, expected {n} (one per {what})", path=("params", key))


def check_matrix(rows: list[list[Any]], n_rows: int, n_cols: int, key: str, row_what: str, col_what: str) -> None:
    """BadInput at params.<key>[i] unless `rows` is n_rows × n_cols."""
    if len(rows) != n_rows:
        raise BadInput(f"has {len(rows)} rows, expected {n_rows} (one per {row_what})", path=("params", key))
    for i, row in enumerate(rows):
        if len(row) != n_cols:
            raise BadInput(
                f"row {i} has {len(row)} values, expected {n_cols} (one per {col_what})",
                path=("params", key, i),
            )


def step_rows(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """Indices of the rows at which the loop steps a model of update period `period_s`.

    Same rule as Model.predict and the loop: step at the first row, then at the first
    row at or after the previous step time plus the period.
    """
    if period_s <= 0:
        return np.arange(t_s.size)
    out = []
    next_t = -np.inf
    for i, t in enumerate(t_s):
        if t >= next_t:
            out.append(i)
            next_t = t + period_s
    return np.asarray(out, dtype=np.intp)


class Model(ABC):
    """A thermal-error model.

    `inputs` are signal names (the frame supplies them in this order), `outputs`
    axis names. `evaluate` writes the predicted thermal error in µm per output axis
    (the correction is its negative; the guard does that). `update_period_s` > 0
    makes the loop call `evaluate` only that often (AR(1) steps every Δτ) and hold
    the output between steps.
    """

    kind: ClassVar[str]
    Params: ClassVar[type[Strict]]
    update_period_s: float = 0.0
    # set by a model whose memory changed outside `start` (a contribution of a sum started): the
    # loop hands the state on for persistence and clears it
    state_dirty: bool = False
    # where the model's own events go (t_s, subject, event, reason): the guard's (compd.cycle.pipeline);
    # None: nowhere (a shadow's)
    emit: Callable[[float, str, str, str], None] | None = None
    # the parts summed into each axis's prediction, (name, axis) each, and per part what it adds (after
    # its own limits), its model's own prediction, its state and clamp flag: none for one model
    # (compd.cycle.contributions has them)
    part_names: tuple[tuple[str, str], ...] = ()
    part_um: np.ndarray = np.zeros(0)
    part_raw_um: np.ndarray = np.zeros(0)
    part_state: np.ndarray = np.zeros(0, dtype=np.uint8)
    part_clamped: np.ndarray = np.zeros(0, dtype=bool)
    # the params `compd status` shows as the model's key coefficients (`coefficients`)
    summary_keys: ClassVar[tuple[str, ...]] = ()
    per_axis_keys: ClassVar[tuple[str, ...]] = ()  # those of them that hold one value per output axis

    def __init__(
        self,
        params: Strict,
        inputs: list[str],
        outputs: list[str],
        fit: dict[str, Any] | None = None,
    ) -> None:
        self.check_wiring(params, inputs, outputs)
        self.params = params
        self.inputs = list(inputs)
        self.outputs = list(outputs)
        self.fit_info = dict(fit or {})
        self.file: str | None = None  # the model file it was loaded from (set by the pipeline)
        self.sha256: str | None = None  # what it is (compd.config.model_sha256; set by the pipeline for a shadow)
        # the inputs' sensor lag compensated before every evaluation (None: no input is led)
        self.lead: InputLead | None = None
        if isinstance(params, LeadParams) and params.lead_s and any(v > 0 for v in params.lead_s):
            self.lead = InputLead(params.lead_s, params.lead_filter_s or [])

    @classmethod
    def check_wiring(cls, params: Strict, inputs: list[str], outputs: list[str]) -> None:
        """Raise BadInput if the number of inputs or outputs does not suit the params.

        The BadInput's key path is relative to the model section: ("params", key, ...),
        ("inputs",) or ("outputs",), so the config loader can name the line.
        """
        if not outputs:
            raise BadInput("a model needs at least one output axis", path=("outputs",))
        if len(set(inputs)) != len(inputs):
            raise BadInput("the model's inputs name a signal twice", path=("inputs",))
        if len(set(outputs)) != len(outputs):
            raise BadInput("the model's outputs name an axis twice", path=("outputs",))
        if isinstance(params, LeadParams) and params.lead_s is not None and len(params.lead_s) != len(inputs):
            raise BadInput(
                f"has {len(params.lead_s)} values, expected {len(inputs)} (one per input)", path=("params", "lead_s")
            )

    def start(self, x: np.ndarray, t_s: float) -> None:
        """Called once with the first good input vector (capture references such as T0)."""

    @abstractmethod
    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """Write the predicted thermal error (µm) per output axis into `out` (from inputs already led)."""

    def run(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """The loop's call: lead the inputs (their sensors' lag, `lead_s`), then `evaluate`."""
        if self.lead is not None:
            x = self.lead.step(x, t_s)
        self.evaluate(x, t_s, out)

    def run_degraded(self, x: np.ndarray, good: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """`run` with some inputs bad: the good ones led, then `evaluate_degraded`."""
        if self.lead is not None:
            x = self.lead.step(x, t_s, good)
        self.evaluate_degraded(x, good, t_s, out)

    @property
    def supports_degraded(self) -> bool:
        """True when the model can predict with some inputs bad (`evaluate_degraded`)."""
        return False

    def evaluate_degraded(self, x: np.ndarray, good: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """Predict from the inputs where `good` is True; NaN for axes it cannot serve."""
        out.fill(np.nan)

    @property
    def starts_by_parts(self) -> bool:
        """True when the model may run before every input has been good once (a sum of
        contributions starts each on its own inputs); False: `start` waits for all of them."""
        return False

    def linear_terms(self) -> list[tuple[float, float]] | None:
        """Per output axis (error slope µm/mm, reference position P0 mm) of the last
        evaluation, its output being the error at P0, for a sink that applies a
        position-dependent correction (Siemens tanβ, P0); None when the model is not
        linear in the position (the default), or not in its present mode."""
        return None

    def predict(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Batch prediction over a log: X (n × inputs) → (n × outputs), µm, as the loop's `run`
        row by row would give it: the inputs led at the rows the model evaluates (every row, or
        every update_period_s), then `predict_rows`."""
        X = np.asarray(X, dtype=float)
        if self.lead is not None and X.shape[0]:
            t = np.asarray(t_s, dtype=float)
            rows = step_rows(t, self.update_period_s)
            X = X.copy()
            X[rows] = self.lead.filter(X[rows], t[rows])
        return self.predict_rows(X, t_s)

    def predict_rows(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Batch prediction from inputs already led: X (n × inputs) → (n × outputs), µm.

        The default steps `evaluate` through the rows (honouring update_period_s),
        starting the model on the first row.
        """
        n = X.shape[0]
        out = np.zeros((n, len(self.outputs)))
        if n == 0:
            return out
        self.start(X[0], float(t_s[0]))
        row = np.zeros(len(self.outputs))
        next_t = -np.inf
        for i in range(n):
            if t_s[i] >= next_t:
                self.evaluate(X[i], float(t_s[i]), row)
                next_t = t_s[i] + self.update_period_s if self.update_period_s > 0 else -np.inf
            out[i] = row
        return out

    def get_state(self) -> dict[str, Any]:
        """The model's memory (for persistence); plain JSON types."""
        return {}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        """Restore memory saved `elapsed_s` ago."""

    def to_dict(self) -> dict[str, Any]:
        """The model file (docs/formats.md): kind, inputs, outputs, params, fit (a model without a
        lead writes no lead keys, as files before them)."""
        params = self.params.model_dump(mode="json")
        for key in ("lead_s", "lead_filter_s"):
            if params.get(key, 0) is None:
                del params[key]
        return {
            "kind": self.kind,
            "inputs": list(self.inputs),
            "outputs": list(self.outputs),
            "params": params,
            "fit": self.fit_info,
        }

    def coefficients(self) -> dict[str, Any]:
        """The key params (`summary_keys`), rounded to 4 significant digits: a matrix of one
        column per output axis becomes {axis: column}, a list of `per_axis_keys` {axis: value};
        a long list its length."""
        dump = self.params.model_dump(mode="json")
        out: dict[str, Any] = {}
        for key in self.summary_keys:
            value = dump.get(key)
            if value is None:
                continue
            if (
                isinstance(value, list)
                and value
                and all(isinstance(r, list) for r in value)
                and all(len(r) == len(self.outputs) for r in value)
            ):
                value = {axis: [row[j] for row in value] for j, axis in enumerate(self.outputs)}
            elif key in self.per_axis_keys and isinstance(value, list) and len(value) == len(self.outputs):
                value = dict(zip(self.outputs, value, strict=True))
            out[key] = _compact(value)
        return out

    def get_status(self) -> dict[str, Any]:
        """Kind, wiring, the file and its fit (when fitted_at, on what, how well), the key
        coefficients and the model's memory (the latched T0 where it has one). Not for the
        cycle: it allocates."""
        fit = {
            k: self.fit_info[k] for k in ("fitted_at", "log", "rows", "rmse_um", "compd_version") if k in self.fit_info
        }
        return {
            "kind": self.kind,
            "inputs": self.inputs,
            "outputs": self.outputs,
            "file": self.file,
            "fit": fit,
            "coefficients": self.coefficients(),
            "state": self.get_state(),
        }


class ModelStage:
    """The rule by which a cycle steps one model: started on its first good input vector, run when
    due and held until `update_period_s` has passed, predicting from the good inputs where it can
    when some are bad (`degraded`), else NaN. The loop's model stage, each contribution of a sum
    (compd.cycle.contributions) and the shadow (compd.cycle.shadow) step their models by it."""

    def __init__(self, model: Model) -> None:
        self.model = model
        self.started = False
        self.next_s = -math.inf  # when the model is next due
        self.degraded = False  # the last step predicted from a reduced set of inputs

    def step(self, x: np.ndarray, good: np.ndarray, ok: bool, now_s: float, out: np.ndarray) -> bool:
        """One step on the inputs `x` (`ok`: all good; else `good` says which are), the prediction
        into `out`. True when the model's memory changed in a way worth keeping (it started, it
        stepped on its update period, or it says so: `state_dirty`)."""
        m = self.model
        kept = False
        if ok:
            if not self.started:
                m.start(x, now_s)
                self.started = True
                kept = True
            m.run(x, now_s, out)
            if m.update_period_s > 0:
                self.next_s = now_s + m.update_period_s
                kept = True
            self.degraded = False
        elif (self.started or m.starts_by_parts) and m.supports_degraded:
            m.run_degraded(x, good, now_s, out)  # predict from the others where they carry the information
            self.degraded = True
        else:
            out.fill(math.nan)
        if m.state_dirty:
            m.state_dirty = False
            kept = True
        return kept


def _compact(value: Any, max_items: int = 12) -> Any:
    """Numbers to 4 significant digits; a list longer than `max_items` as its length."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int | float):
        return float(f"{value:.4g}") if isinstance(value, float) else value
    if isinstance(value, dict):
        return {str(k): _compact(v, max_items) for k, v in value.items()}
    if isinstance(value, list | tuple):
        if len(value) > max_items:
            return f"[{len(value)} values]"
        return [_compact(v, max_items) for v in value]
    return str(value)

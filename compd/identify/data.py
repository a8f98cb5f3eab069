"""Shared data preparation of every fit: pick columns from a log, refuse data no fit can use, validate options."""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from pydantic import ValidationError

from compd.config import Strict
from compd.errors import BadInput
from compd.log import Log, error_axis

if TYPE_CHECKING:
    from collections.abc import Sequence

    from compd.models.base import Model

OptionsT = TypeVar("OptionsT", bound=Strict)


@dataclass
class FitResult:
    """What a fit returns: the model and a JSON-able report."""

    model: Model
    report: dict[str, Any] = field(default_factory=dict)


def validate_options(kind: str, schema: type[OptionsT], options: dict[str, Any]) -> OptionsT:
    """`options` validated against the kind's option schema; a bad one is BadInput naming it."""
    try:
        return schema.model_validate(options)
    except ValidationError as e:
        err = e.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "option"
        known = ", ".join(sorted(schema.model_fields)) or "none"
        if err["type"] == "extra_forbidden":
            msg = f"unknown fit option for {kind} (known: {known})"
        else:
            msg = err["msg"] + (f" (got {err['input']!r})" if "input" in err else "")
        raise BadInput(msg, path=f"--option {key}") from None


def default_inputs(log: Log, inputs: Sequence[str] | None) -> list[str]:
    """The named inputs, or every temperature column of the log (compd.log.is_temperature_column)."""
    if inputs:
        return list(inputs)
    names = log.temperature_columns()
    if not names:
        raise BadInput("the log has no temperature columns to use as inputs", file=log.file)
    return names


def default_targets(log: Log, targets: Sequence[str] | None) -> list[str]:
    """The named targets, or every `err_<axis>_um` column of the log."""
    names = list(targets) if targets else log.error_columns()
    if not names:
        raise BadInput("the log has no err_<axis>_um column to fit to", file=log.file)
    for n in names:
        log.index(n)
    return names


def axis_names(targets: Sequence[str]) -> list[str]:
    """`err_x1_um` → `x1`; any other target column keeps its own name."""
    return [error_axis(t) or t for t in targets]


def columns(log: Log, names: Sequence[str]) -> np.ndarray:
    """Columns `names` (n × k); a missing column or an empty/NaN cell is BadInput."""
    X = log.matrix(names)
    bad = ~np.isfinite(X)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise BadInput(
            "empty or non-finite cell in a column the fit needs",
            file=log.file,
            line=int(row) + 2,
            path=names[int(col)],
        )
    return X


def require_rows(log: Log, n: int, need: int, why: str) -> None:
    """BadInput unless `n` ≥ `need` rows."""
    if n < need:
        raise BadInput(f"{n} rows are too few: {why} needs at least {need}", file=log.file)


def check_not_constant(log: Log, X: np.ndarray, names: Sequence[str]) -> None:
    """BadInput naming the first column of X that never changes (it carries no information)."""
    for j, name in enumerate(names):
        col = X[:, j]
        if col.size and np.ptp(col) <= 1e-12 * max(1.0, float(np.max(np.abs(col)))):
            raise BadInput("the column is constant: it cannot enter the fit", file=log.file, path=name)


def progress(iterable: Iterable[Any], desc: str, total: int | None = None) -> Iterable[Any]:
    """A progress bar on stderr that appears only when the work takes over a second (tqdm)."""
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a core dependency
        return iterable
    tqdm.monitor_interval = 0  # no monitor thread: a fit leaves nothing running behind it
    return tqdm(iterable, desc=desc, total=total, delay=1.0, leave=False, file=sys.stderr)


HOLDOUT_BLOCKS = 3  # the log in three contiguous time blocks: two forward-chained folds
HELD_OUT_METHOD = (
    f"forward-chained blocks: the log in {HOLDOUT_BLOCKS} time blocks, each block after the first"
    " predicted by a fit on the blocks before it"
)


def holdout_edges(n: int) -> np.ndarray:
    """Row indices bounding the HOLDOUT_BLOCKS time blocks of an n-row log (block k is edges[k]:edges[k+1])."""
    return np.linspace(0, n, HOLDOUT_BLOCKS + 1).astype(int)


def forward_fold_errors(
    log: Log, targets: Sequence[str], fit_on: Callable[[Log], FitResult]
) -> list[tuple[np.ndarray, np.ndarray] | str]:
    """Per forward-chained fold, (sum of squared errors µm², rows) per target, or why the fold could not be fitted.

    Fold k fits on the blocks before block k (a contiguous stretch from the log's start, so a
    model with memory starts as it would on the machine), predicts the whole log and is scored
    on block k only. Scoring rows next to training rows would flatter a model that follows the
    temperatures closely; predicting forward does not.
    """
    edges = holdout_edges(len(log))
    Y = columns(log, targets)
    folds: list[tuple[np.ndarray, np.ndarray] | str] = []
    for k in range(1, HOLDOUT_BLOCKS):
        try:
            model = fit_on(Log(log.file, log.columns, log.data[: edges[k]])).model
        except (BadInput, ValidationError, ValueError, np.linalg.LinAlgError) as exc:
            folds.append(f"block {k + 1}: {exc}")
            continue
        pred = model.predict(log.matrix(model.inputs), log.t_s)
        out = [model.outputs.index(a) if a in model.outputs else 0 for a in map(error_axis, targets)]
        r = (Y - pred[:, out])[edges[k]: edges[k + 1]]
        ok = np.isfinite(r)
        folds.append(((np.where(ok, r, 0.0) ** 2).sum(axis=0), ok.sum(axis=0)))
    return folds


def compare_forms(
    log: Log, target: str, forms: dict[str, Callable[[Log], FitResult]]
) -> tuple[dict[str, float | str], list[int]]:
    """Held-out RMSE (µm) of each form over the forward-chained folds that every form could be fitted on.

    Returns ({form: RMSE, or why it could not be scored}, the folds used, 1-based blocks)."""
    folds = {name: forward_fold_errors(log, [target], fit_on) for name, fit_on in forms.items()}
    usable = [k for k in range(HOLDOUT_BLOCKS - 1) if all(not isinstance(f[k], str) for f in folds.values())]
    out: dict[str, float | str] = {}
    for name, f in folds.items():
        scored = [f[k] for k in usable]
        count = sum(int(c[0]) for _, c in scored)  # type: ignore[misc]
        if count:
            out[name] = math.sqrt(sum(float(sq[0]) for sq, _ in scored) / count)  # type: ignore[misc]
        else:
            out[name] = "; ".join(x for x in f if isinstance(x, str)) or "no held-out rows"
    return out, [k + 2 for k in usable]

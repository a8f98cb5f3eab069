"""Shared data preparation of every fit: pick columns from a log, refuse data no fit can use, validate options."""

from __future__ import annotations

import re
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from pydantic import ValidationError

from compd.core.config import Strict
from compd.core.errors import BadInput
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


AMBIENT_NAME = re.compile(r"amb|room|air", re.IGNORECASE)


def ambient_columns(log: Log) -> list[str]:
    """The temperature columns whose names say they read the room's air (amb, room, air)."""
    return [c for c in log.temperature_columns() if AMBIENT_NAME.search(c)]


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


def target_columns(log: Log, names: Sequence[str]) -> np.ndarray:
    """Target columns (n × k), NaN where the error was not measured (or a held-out fold hides it).

    A fit takes its loss over the rows whose targets are all finite (`measured_rows`) while its
    inputs run through every row, so a model with memory (the AR(1) state, a sensor's lag) is
    simulated through the rows it does not fit. An infinite cell, or a target never measured, is
    BadInput naming the column."""
    Y = log.matrix(names)
    bad = np.isinf(Y)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise BadInput("infinite cell in a target column", file=log.file, line=int(row) + 2, path=names[int(col)])
    for j, name in enumerate(names):
        if not np.isfinite(Y[:, j]).any():
            raise BadInput("the target column has no measured error", file=log.file, path=name)
    return Y


def measured_rows(Y: np.ndarray) -> np.ndarray:
    """Rows where every target (column of Y) is finite: the rows a fit's loss counts."""
    Y = np.asarray(Y, dtype=float)
    return np.isfinite(Y).all(axis=1) if Y.ndim == 2 else np.isfinite(Y)


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
    """A progress bar on stderr that appears only when the work takes over a second (tqdm), and only
    when stderr is a terminal: into a file or a pipe (a log, a unit's journal) its redraws would be
    thousands of lines, so there the iterable is returned as it is."""
    isatty = getattr(sys.stderr, "isatty", None)
    if not (callable(isatty) and isatty()):
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a core dependency
        return iterable
    tqdm.monitor_interval = 0  # no monitor thread: a fit leaves nothing running behind it
    return tqdm(iterable, desc=desc, total=total, delay=1.0, leave=False, file=sys.stderr)

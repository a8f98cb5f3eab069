"""Held-out scoring that looks like an unseen day.

The log is cut into folds at its days or duty changes, each predicted by a fit on the rest.

Every choice a fit makes beyond its coefficients (LVR's components, the feed axis's form,
AR(1)'s C1 by speed, a sensor's lag compensation) and every comparison a report prints
(the fitted kind against the MLR baseline) is scored the same way:

* the log is cut into folds: its days when gaps in t_s separate several (a log of several
  days in one file); else, when the machine runs at two or more duty levels (spindle speeds,
  feeds: motor current levels), one fold per level — its runs with the pauses after them —
  so each level is predicted by a fit that never saw it, as an unseen day's speeds are; else
  `FOLDS` stretches of about equal length whose edges move to the nearest change of duty
  (a speed level, an axis starting or stopping, a current level) within a quarter of a fold,
  so a fold holds whole runs and pauses;
* fold k is predicted by a fit on the log with the errors of fold k hidden (NaN): the
  fit's loss counts the other folds' rows only, while its inputs run through every row,
  so a model with memory (the AR(1) state, a sensor's lag, the feed axis's heat) comes
  into the fold as it would on the machine;
* the score is the RMS of the fold's prediction error, pooled over the folds.

Each fold's fit sees rows before and after it, so a fold in the middle of the day is
interpolated in time but not in duty: its runs and pauses are not in the fit. Scoring
rows next to training rows would flatter a model that follows noise; a fold of hours
has few such rows.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from pydantic import ValidationError

from compd.core.errors import BadInput
from compd.identify.data import FitResult, columns
from compd.log import Log, error_axis

FOLDS = 4  # an unseen day against three quarters of the training data
GAP_S = 3600.0  # a pause in t_s this long (and 10 logging periods) separates two days
SPEED_STEP = 0.05  # speeds within 5 % (and 50 rpm) are one duty level
METHOD = (
    "held out: the log in folds (its days when gaps separate them; else one per duty level, its runs and the pauses"
    f" after them, where it runs at two or more; else {FOLDS} equal stretches moved to the nearest duty change),"
    " each fold predicted by a fit that never saw its errors"
)

# a held-out difference smaller than this is no difference: far below the word's 1 µm LSB and a
# probe's σ, it is numerical noise on a log the simpler form already fits
FLOOR_UM = 0.01

FoldScore = tuple[np.ndarray, np.ndarray] | str  # (sum of squared errors µm², rows) per target, or why not


def duty_state(log: Log) -> np.ndarray | None:
    """Per row what the machine does, as one integer per distinct state (0 = idle: no spindle turning,
    no axis moving): the spindle's speed level, each axis moving or standing, each motor current's
    level. None when the log has no duty column."""
    cols, busy = [], np.zeros(len(log), dtype=bool)
    for name in log.columns:
        v = np.nan_to_num(log.col(name))
        if name == "speed_rpm" or name.startswith("current_"):
            ref = max(float(np.max(np.abs(v))) if v.size else 0.0, 1e-9)
            step = max(SPEED_STEP * ref, 50.0 if name == "speed_rpm" else 0.0)
            level = np.round(np.abs(v) / step)
            cols.append(level)
            if name == "speed_rpm":
                busy |= level > 0
        elif name.startswith("pos_") and name.endswith("_mm"):
            moving = np.r_[False, np.abs(np.diff(v)) > 0.5]
            cols.append(moving.astype(float))
            busy |= moving
            cols += _stroke_levels(v, log.t_s, moving)
    if not cols:
        return None
    _, state = np.unique(np.column_stack(cols), axis=0, return_inverse=True)
    state = np.asarray(state).reshape(-1) + 1
    state[~busy] = 0
    return state


STROKE_WINDOW_S = 120.0  # an axis's stroke: the span of its positions over two minutes
STROKE_STEP = 0.25  # strokes whose span or middle differ by a quarter of the travel are two duties


def _stroke_levels(pos_mm: np.ndarray, t_s: np.ndarray, moving: np.ndarray) -> list[np.ndarray]:
    """Per row the span and the middle of the stroke a moving axis runs (the positions it covers
    within STROKE_WINDOW_S), in steps of STROKE_STEP of the whole travel; 0 while it stands. A partial
    stroke at one end heats that end: another duty than the full stroke."""
    n = pos_mm.size
    travel = float(np.ptp(pos_mm)) if n else 0.0
    if n < 3 or travel <= 0:
        return []
    steps = np.diff(t_s)
    dt = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 1.0
    half = max(1, int(round(0.5 * STROKE_WINDOW_S / dt)))
    padded = np.pad(pos_mm, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
    lo, hi = windows.min(axis=1), windows.max(axis=1)
    step = STROKE_STEP * travel
    span = np.where(moving, np.round((hi - lo) / step) + 1, 0.0)
    middle = np.where(moving, np.round((0.5 * (lo + hi) - pos_mm.min()) / step) + 1, 0.0)
    return [span, middle]


def duty_changes(log: Log) -> np.ndarray:
    """Rows at which the machine's duty changes (the first row of each new duty)."""
    state = duty_state(log)
    if state is None:
        return np.zeros(0, dtype=np.intp)
    return np.flatnonzero(state[1:] != state[:-1]) + 1


def days(t_s: np.ndarray) -> list[tuple[int, int]]:
    """(first, end) rows of the stretches between gaps of ≥ GAP_S s and ≥ 10 median steps."""
    n = t_s.size
    if n < 2:
        return [(0, n)]
    dt = np.diff(t_s)
    limit = max(GAP_S, 10.0 * float(np.median(dt)))
    edges = [0, *(np.flatnonzero(dt >= limit) + 1).tolist(), n]
    return list(zip(edges[:-1], edges[1:], strict=True))


Fold = list[tuple[int, int]]  # the (first, end) row ranges a fold hides


def level_folds(log: Log) -> list[Fold]:
    """One fold per duty level the log runs at, when it runs at two or more: each run at the level
    with the pause that follows it (the cooling from it) until the next run. Hiding a level is what
    an unseen day does to a model: a speed or feed it was not fitted at. [] when the log has fewer
    than two levels, or a level shorter than 5 % of the log."""
    state = duty_state(log)
    if state is None:
        return []
    n = len(state)
    runs: dict[int, Fold] = {}
    k = 0
    while k < n:
        if state[k] == 0:
            k += 1
            continue
        j = k
        while j + 1 < n and state[j + 1] in (0, state[k]) and not (state[j] == 0 and state[j + 1] != 0):
            j += 1
        runs.setdefault(int(state[k]), []).append((k, j + 1))
        k = j + 1
    if len(runs) < 2:
        return []
    folds = list(runs.values())
    if min(sum(hi - lo for lo, hi in f) for f in folds) < 0.05 * n:
        return []
    return folds


def folds(log: Log, n_folds: int = FOLDS) -> tuple[list[Fold], str]:
    """The held-out folds (row ranges each) and how they were cut: `days`, `levels` or `duty`."""
    n = len(log)
    d = days(log.t_s)
    if len(d) >= 2 and min(hi - lo for lo, hi in d) >= n / (4 * len(d)):
        return [[r] for r in d], "days"
    by_level = level_folds(log)
    if by_level:
        return by_level, "levels"
    k = max(2, min(n_folds, n // 4))
    changes = duty_changes(log)
    edges = [0]
    for j in range(1, k):
        target = j * n / k
        near = changes[np.abs(changes - target) <= n / (4 * k)] if changes.size else changes
        edge = int(near[np.argmin(np.abs(near - target))]) if near.size else int(round(target))
        if edge > edges[-1]:
            edges.append(edge)
    edges.append(n)
    return [[(lo, hi)] for lo, hi in zip(edges[:-1], edges[1:], strict=True)], "duty"


def hide(log: Log, targets: Sequence[str], fold: Fold) -> Log:
    """A copy of the log with the targets' cells in the fold's rows blank (NaN)."""
    data = log.data.copy()
    cols = [log.index(name) for name in targets]
    for lo, hi in fold:
        data[lo:hi, cols] = np.nan
    return Log(log.file, log.columns, data)


def _rows(fold: Fold) -> np.ndarray:
    return np.concatenate([np.arange(lo, hi) for lo, hi in fold]) if fold else np.zeros(0, dtype=np.intp)


def ranges(mask: np.ndarray) -> Fold:
    """The (first, end) ranges of the runs of True in a boolean row mask."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist(), strict=True))


def on_rows(fold: Fold, keep: np.ndarray) -> Fold:
    """A fold of a log's rows as ranges of the subset `keep` (a boolean row mask) numbers them."""
    m = np.zeros(len(keep), dtype=bool)
    for lo, hi in fold:
        m[lo:hi] = True
    return ranges(m[np.asarray(keep, bool)])


FIT_ERRORS = (BadInput, ValidationError, ValueError, np.linalg.LinAlgError)


def fold_errors(
    log: Log,
    targets: Sequence[str],
    fit_on: Callable[[Log], FitResult],
    cut: list[Fold] | None = None,
) -> list[FoldScore]:
    """Per fold, (sum of squared errors µm², rows) per target on the fold's rows with the error
    measured, the fold predicted by `fit_on` the log with that fold's errors hidden; or why the
    fold could not be fitted."""
    cut = folds(log)[0] if cut is None else cut
    Y = log.matrix(list(targets))
    out: list[FoldScore] = []
    for k, fold in enumerate(cut):
        rows = _rows(fold)
        if not np.isfinite(Y[rows]).any():
            out.append(f"fold {k + 1}: no measured error")
            continue
        try:
            model = fit_on(hide(log, targets, fold)).model
            fresh = type(model)(model.params, model.inputs, model.outputs, model.fit_info)  # from a cold start
            pred = fresh.predict(columns(log, model.inputs), log.t_s)
        except FIT_ERRORS as exc:
            out.append(f"fold {k + 1}: {exc}")
            continue
        cols = [model.outputs.index(a) if a in model.outputs else 0 for a in map(error_axis, targets)]
        r = (Y - pred[:, cols])[rows]
        ok = np.isfinite(r)
        out.append(((np.where(ok, r, 0.0) ** 2).sum(axis=0), ok.sum(axis=0)))
    return out


def pooled_rmse(scores: Sequence[FoldScore], n_targets: int) -> np.ndarray:
    """RMS (µm) per target over the folds that could be fitted; ValueError if one could not."""
    sq, count = np.zeros(n_targets), np.zeros(n_targets)
    for f in scores:
        if isinstance(f, str):
            raise ValueError(f)
        sq += f[0]
        count += f[1]
    return np.sqrt(sq / np.maximum(count, 1))


def held_out_rmse(log: Log, targets: Sequence[str], fit_on: Callable[[Log], FitResult]) -> np.ndarray:
    """Held-out RMSE per target (µm), every fold fitted (ValueError naming the fold that cannot be)."""
    return pooled_rmse(fold_errors(log, targets, fit_on), len(targets))


def compare(
    log: Log, target: str, forms: dict[str, Callable[[Log], FitResult]]
) -> tuple[dict[str, float | str], list[int]]:
    """Held-out RMSE (µm) of each form over the folds every form could be fitted on.

    Returns ({form: RMSE, or why it could not be scored}, the folds used, 1-based)."""
    cut = folds(log)[0]
    scores = {name: fold_errors(log, [target], fit_on, cut) for name, fit_on in forms.items()}
    usable = [k for k in range(len(cut)) if all(not isinstance(f[k], str) for f in scores.values())]
    out: dict[str, float | str] = {}
    for name, f in scores.items():
        used = [f[k] for k in usable]
        count = sum(int(c[0]) for _, c in used)  # type: ignore[misc]
        if count:
            out[name] = math.sqrt(sum(float(sq[0]) for sq, _ in used) / count)  # type: ignore[misc]
        else:
            out[name] = "; ".join(x for x in f if isinstance(x, str)) or "no held-out rows"
    return out, [k + 1 for k in usable]


def clearly_better(new_um: float, old_um: float, margin: float) -> bool:
    """True when a held-out RMSE `new_um` beats `old_um` by the factor `margin` (0.95: 5 %) and by
    more than FLOOR_UM: the more complex form has to earn its place."""
    return new_um < margin * old_um and old_um - new_um > FLOOR_UM

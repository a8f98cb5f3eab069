"""Identifying the LVR model: PLS on temperature rises, components by blocked cross-validation or the paper's LOO Q².

The PLS regression itself (the paper's algorithm, pure numpy) is compd.models.lvr.fit_pls;
this module chooses how many components it keeps and fits the model from a log.

Two ways to choose the number of components (`--option selection=...`):

* `loo`, paper 002: keep component h while the leave-one-out
  Q²_h = 1 − PRESS_h / SS_(h−1) ≥ 0.0975 (= 1 − 0.95²).
* `blocked` (compd's form, the default): the fit rows are cut into contiguous stretches
  in time (the log's days, when gaps separate them; else `cv_blocks` equal stretches),
  each stretch is predicted by a fit on the others with a guard band of rows next to it
  left out, and the fit keeps the fewest components whose held-out error (PRESS, summed
  over the stretches) is within 5 % RMS of the best count's: no more components cut it
  by Q² ≥ 0.0975 (`select_blocked`). The report's Q²_h = 1 − PRESS_h / PRESS_(h−1),
  PRESS_0 that of the training rows' mean.
  A 1 Hz log is strongly autocorrelated (the noise of a thermal log is slow: sensor drift,
  air currents, unmodelled heat paths), so leaving one row out leaves its neighbours, with
  nearly the same noise, in the fit: extra components that fit that noise also "predict"
  the left-out row, and LOO over-selects. A held-out stretch has no such neighbours.

Exact leave-one-out without n refits: with the data centred on the full mean, the
left-out set's centred cross products are X'X − (1 + 1/m) x_i x_i' and
X'Y − (1 + 1/m) x_i y_i' (m = n − 1), its standard deviations follow from their
diagonals, and a kernel PLS (Dayal & MacGregor 1997, algorithm 1: deflate only X'Y)
on those p × p and p × q matrices gives the same components as NIPALS on the
left-out data. All n problems are solved at once as stacked arrays: O(n p² h).
Blocked cross-validation refits K times, each fit giving all h at once (`coef_path`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.identify import holdout
from compd.identify.data import FitResult, axis_names, measured_rows, require_rows, validate_options
from compd.identify.mlr import linear_data, rise_stats, rises
from compd.log import Log
from compd.models.lvr import LVR, LVRParams, PLSModel, as_xy, fit_pls

Q2_LIMIT = 0.0975  # 1 − 0.95² (paper 002)
GAP_S = 3600.0  # a pause in t_s at least this long (and 10 logging periods) separates two stretches
GUARD_ACF = 0.05  # the guard band ends where the residuals' autocorrelation falls below this


def coef_path(model: PLSModel) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (h × p × q) and intercepts (h × q), original units, of the fits with 1 … h components.

    The components of a PLS fit are nested: the fit with k components is the first k of
    them, B_k = W_k (P_k' W_k)⁻¹ R_k' (paper 002, eq. 8), so one fit with h components
    gives all h models.
    """
    W, P, Rl = model.x_weights_, model.x_loadings_, model.y_loadings_
    A = W.shape[1]
    coefs = np.empty((A, W.shape[0], Rl.shape[0]))
    for k in range(1, A + 1):
        B_std = W[:, :k] @ np.linalg.solve(P[:, :k].T @ W[:, :k], Rl[:, :k].T)
        coefs[k - 1] = B_std * model.y_std_[None, :] / model.x_std_[:, None]
    intercepts = model.y_mean_[None, :] - np.einsum("p,hpq->hq", model.x_mean_, coefs)
    return coefs, intercepts


Block = tuple[int, int] | list[tuple[int, int]]  # (first, end) rows, or several such ranges (a duty level)


def _block_ranges(block: Block) -> list[tuple[int, int]]:
    return [block] if isinstance(block, tuple) else list(block)  # type: ignore[list-item]


def blocked_press(
    X: np.ndarray, Y: np.ndarray, max_components: int, blocks: list[Block], guard_rows: int
) -> np.ndarray:
    """PRESS of each held-out block, K × (h + 1), in full-data standardised Y units.

    Block k is rows `blocks[k]` = (first, end) of X and Y, contiguous in time, or a list of
    such ranges (a duty level's runs, compd.identify.holdout.level_folds). It is
    predicted by a fit on the rows outside it less `guard_rows` rows on each side of it
    (they share its noise: `guard_rows_from_residuals`), standardised on those rows as
    a fit on them alone is. Column 0 is the model without components (the training
    rows' mean), column h the fit with h components. ValueError if a block leaves fewer
    than `rows_needed` rows to fit.
    """
    X, Y, n, _, _ = as_xy(X, Y)
    A = max_components
    y_std_full = Y.std(axis=0, ddof=1)
    y_std_full[y_std_full == 0.0] = 1.0
    press = np.zeros((len(blocks), A + 1))
    for k, block in enumerate(blocks):
        held = np.zeros(n, dtype=bool)
        train = np.ones(n, dtype=bool)
        for lo, hi in _block_ranges(block):
            held[lo:hi] = True
            train[max(lo - guard_rows, 0) : hi + guard_rows] = False
        n_train = int(train.sum())
        if n_train < rows_needed(A):
            first, last = int(np.argmax(held)), n - 1 - int(np.argmax(held[::-1]))
            raise ValueError(
                f"holding out rows {first}..{last} leaves {n_train} rows to fit, {A} components need {rows_needed(A)}"
            )
        Xt, Yt = X[train], Y[train]
        Xv, Yv = X[held], Y[held]
        res0 = (Yv - Yt.mean(axis=0)) / y_std_full
        press[k, 0] = float(np.sum(res0 * res0))
        coefs, intercepts = coef_path(fit_pls(Xt, Yt, A))
        for h in range(A):
            res = (Yv - (Xv @ coefs[h] + intercepts[h])) / y_std_full
            press[k, h + 1] = float(np.sum(res * res))
    return press


def loo_press(X: np.ndarray, Y: np.ndarray, max_components: int, chunk_elems: int = 4_000_000) -> np.ndarray:
    """Exact leave-one-out PRESS_h, h = 1..max_components, in full-data standardised Y units.

    Each left-out fit re-standardises on its own n − 1 rows, as a naive refit does.
    See the module docstring for the downdate; samples are processed in chunks of
    about `chunk_elems` / p² at a time to bound memory.
    """
    X, Y, n, p, q = as_xy(X, Y)
    A = max_components
    m = n - 1
    if m < 2:
        raise ValueError("leave-one-out needs at least 3 rows")
    Xc = X - X.mean(axis=0)
    Yc = Y - Y.mean(axis=0)
    y_std_full = Y.std(axis=0, ddof=1)
    y_std_full[y_std_full == 0.0] = 1.0
    XtX = Xc.T @ Xc
    XtY = Xc.T @ Yc
    ssx = np.diag(XtX)
    ssy = np.sum(Yc * Yc, axis=0)
    g = 1.0 + 1.0 / m
    press = np.zeros(A)
    step = max(1, chunk_elems // max(p * p, 1))
    for lo in range(0, n, step):
        xi = Xc[lo : lo + step]
        yi = Yc[lo : lo + step]
        k = xi.shape[0]
        # Standard deviations of each left-out set (ddof = 1).
        sdx = np.sqrt(np.maximum(ssx - g * xi * xi, 0.0) / (m - 1))
        sdx[sdx == 0.0] = 1.0
        sdy = np.sqrt(np.maximum(ssy - g * yi * yi, 0.0) / (m - 1))
        sdy[sdy == 0.0] = 1.0
        XX = XtX[None] - g * xi[:, :, None] * xi[:, None, :]
        XX /= sdx[:, :, None] * sdx[:, None, :]
        XY = XtY[None] - g * xi[:, :, None] * yi[:, None, :]
        XY /= sdx[:, :, None] * sdy[:, None, :]
        z = xi / sdx  # left-out row relative to the full mean, standardised by the LOO sd
        z *= n / m  # x_i − mean_loo = (n/m) xc_i
        target = (n / m) * yi  # y_i − mean_loo
        R = np.zeros((k, p, A))
        Pm = np.zeros((k, p, A))
        B = np.zeros((k, p, q))
        for a in range(A):
            if q == 1:
                w = XY[:, :, 0].copy()
            else:
                M = np.einsum("kpi,kpj->kij", XY, XY)
                _, vecs = np.linalg.eigh(M)
                w = np.einsum("kpq,kq->kp", XY, vecs[:, :, -1])
            w /= np.linalg.norm(w, axis=1, keepdims=True) + 1e-300
            if a:
                c = np.einsum("kpj,kp->kj", Pm[:, :, :a], w)
                r = w - np.einsum("kpj,kj->kp", R[:, :, :a], c)
            else:
                r = w
            XXr = np.einsum("kpq,kq->kp", XX, r)
            tt = np.einsum("kp,kp->k", r, XXr)
            tt = np.where(tt > 1e-300, tt, np.inf)
            p_a = XXr / tt[:, None]
            q_a = np.einsum("kpq,kp->kq", XY, r) / tt[:, None]
            XY -= (tt[:, None] * p_a)[:, :, None] * q_a[:, None, :]
            R[:, :, a] = r
            Pm[:, :, a] = p_a
            B += r[:, :, None] * q_a[:, None, :]
            yhat = np.einsum("kp,kpq->kq", z, B) * sdy
            res = (target - yhat) / y_std_full
            press[a] += float(np.sum(res * res))
    return press


def select_components(
    X: np.ndarray, Y: np.ndarray, max_components: int, limit: float = Q2_LIMIT
) -> tuple[int, list[float], PLSModel]:
    """Q² leave-one-out selection (paper 002): keep component h while Q²_h ≥ `limit`.

    Returns (chosen h ≥ 1, Q²_1..Q²_max, the full-data fit with max_components).
    """
    full = fit_pls(X, Y, max_components)
    press = loo_press(X, Y, max_components)
    q2 = [1.0 - press[h] / full.ss_[h] if full.ss_[h] > 0 else -np.inf for h in range(max_components)]
    chosen = 0
    for v in q2:
        if v >= limit:
            chosen += 1
        else:
            break
    return max(chosen, 1), [float(v) for v in q2], full


def blocked_q2(press: np.ndarray) -> list[float]:
    """Q²_h = 1 − PRESS_h / PRESS_(h−1), h = 1 … A, from `blocked_press` (summed over its blocks).

    The paper's limit 0.0975 = 1 − 0.95² then reads: component h stays if it cuts the
    held-out RMS error of the model with h − 1 components by at least 5 %.
    """
    total = press.sum(axis=0)
    return [float(1.0 - total[h] / total[h - 1]) if total[h - 1] > 0 else -np.inf for h in range(1, total.size)]


def select_blocked(
    X: np.ndarray,
    Y: np.ndarray,
    max_components: int,
    blocks: list[tuple[int, int]],
    guard_rows: int,
    limit: float = Q2_LIMIT,
) -> tuple[int, list[float], np.ndarray]:
    """Blocked cross-validation selection: the fewest components within 5 % RMS of the best held-out error.

    h is the smallest count whose summed held-out PRESS_h satisfies
    PRESS_h (1 − `limit`) ≤ min over all counts tried of PRESS: no count, however many
    more components it adds, cuts the held-out error of h by `limit` or more (0.0975 =
    1 − 0.95²: 5 % of the RMS error, the paper's limit). For one component more this is
    the paper's test with held-out error on both sides of the ratio,
    Q²_h = 1 − PRESS_h / PRESS_(h−1) ≥ `limit` (`blocked_q2`, what the report lists).

    Why this rule. The paper's Q²_h divides the cross-validated PRESS_h by SS_(h−1), the
    residual of the fit to all rows. Leaving one row out, PRESS_(h−1) ≈ SS_(h−1) unless the
    fit is over-fitted already, so the two read alike. A held-out stretch of time is
    predicted by extrapolation and its PRESS stays well above SS: on the simulated
    gantry's training day (the simulator's gantry_train at 60 s, 5 blocks, a guard of 144 rows) the
    second component cuts the blocked PRESS from 393 to 143, but SS_1 is 149, so the
    paper's ratio, Q²_2 = 0.04, would drop the component that axis X2 needs (78 % instead
    of 91 % RMS reduction on the unseen day, open loop). Comparing held-out with held-out
    asks only what components add on data the fit has not seen. A component that fits
    noise does not add: the noise of one stretch does not carry to another, so the
    held-out error grows. Looking past the next component (rather than stopping at the
    first that fails, as the paper does) keeps a useful component that follows a useless
    one: PLS orders components by covariance, not by how well they predict (a 6 h lathe
    log: PRESS 145, 150, 71 for 3, 4, 5 components). The tolerance keeps the fewest
    components when more gain little — the minimum of PRESS alone would follow noise in
    a flat curve. A one-standard-error rule (the spread of the blocks' errors as the
    tolerance) was tried too: a thermal day's stretches differ too much (warm-up, steady
    running, the night) for their spread to be a yardstick; it dropped X2's second
    component with 10 blocks.

    Returns (chosen h ≥ 1, Q²_1..Q²_max, PRESS_0..PRESS_max summed over the blocks).
    """
    press = blocked_press(X, Y, max_components, blocks, guard_rows)
    total = press.sum(axis=0)
    return fewest_within(total[1:], limit), blocked_q2(press), total


def fewest_within(press: np.ndarray, limit: float) -> int:
    """The smallest h (1-based) with `press`[h − 1] (1 − `limit`) ≤ min(`press`); its minimum if none (limit < 0)."""
    press = np.asarray(press, dtype=float)
    ok = press * (1.0 - limit) <= press.min()
    return int(np.argmax(ok)) + 1 if ok.any() else int(np.argmin(press)) + 1


def equal_blocks(n: int, n_blocks: int) -> list[tuple[int, int]]:
    """`n_blocks` contiguous (first, end) row ranges of nearly equal length covering rows 0 … n − 1."""
    edges = np.linspace(0, n, n_blocks + 1).round().astype(int)
    return [(int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]


def stretches(t_s: np.ndarray) -> list[tuple[int, int]]:
    """(first, end) rows of the log's stretches between gaps: steps in t_s of ≥ GAP_S s and ≥ 10 median steps."""
    n = t_s.size
    if n < 2:
        return [(0, n)]
    dt = np.diff(t_s)
    limit = max(GAP_S, 10.0 * float(np.median(dt)))
    edges = [0, *(np.nonzero(dt >= limit)[0] + 1).tolist(), n]
    return list(zip(edges[:-1], edges[1:], strict=True))


def train_rows(n: int, blocks: list[Block], guard_rows: int) -> np.ndarray:
    """Rows each block leaves to fit: n less the block and `guard_rows` rows on each side of its ranges."""
    out = []
    for block in blocks:
        train = np.ones(n, dtype=bool)
        for lo, hi in _block_ranges(block):
            train[max(lo - guard_rows, 0) : hi + guard_rows] = False
        out.append(int(train.sum()))
    return np.array(out)


def held_out_blocks(t_s: np.ndarray, n_blocks: int, need: int) -> tuple[list[tuple[int, int]], str]:
    """The held-out blocks of blocked cross-validation over rows with times `t_s`, and how they were cut.

    `gaps`: the log's stretches between gaps (days logged into one file), when at least
    two remain after each stretch shorter than n / (2 `n_blocks`) rows has been joined to
    its neighbour, and every one leaves at least `need` rows to fit. Otherwise `equal`:
    `n_blocks` stretches of equal length.
    """
    n = t_s.size
    short = n / (2 * n_blocks)
    merged: list[list[int]] = []
    for lo, hi in stretches(t_s):
        if merged and (hi - lo < short or merged[-1][1] - merged[-1][0] < short):
            merged[-1][1] = hi
        else:
            merged.append([lo, hi])
    days = [(lo, hi) for lo, hi in merged]
    if len(days) >= 2 and train_rows(n, days, 0).min() >= need:
        return days, "gaps"
    return equal_blocks(n, n_blocks), "equal"


def max_guard_rows(n: int, blocks: list[tuple[int, int]], need: int) -> int:
    """The widest guard band that still leaves every block `need` rows to fit (0 if none does)."""
    lo, hi = 0, n
    while lo < hi:  # train_rows falls as the guard widens: the last guard with enough rows
        mid = (lo + hi + 1) // 2
        if train_rows(n, blocks, mid).min() >= need:
            lo = mid
        else:
            hi = mid - 1
    return lo


def guard_rows_from_residuals(res: np.ndarray, limit: int) -> int:
    """Guard band, rows: the first lag at which the residuals' autocorrelation falls below GUARD_ACF, ≤ `limit`.

    `res` (n × q) are residuals in time order; their autocorrelation (FFT, averaged over
    the q axes) at lag L is how much noise a row shares with a row L away. Beyond the
    guard band the rows a block is predicted from share at most 5 % of its noise's
    correlation (AR(1) noise with ρ = 0.99 per row: 298 rows).
    """
    r = np.asarray(res, dtype=float)
    if r.ndim == 1:
        r = r[:, None]
    n = r.shape[0]
    if n < 2 or limit <= 0:
        return 0
    r = r - r.mean(axis=0)
    f = np.fft.rfft(r, n=2 * n, axis=0)
    acov = np.fft.irfft(f * np.conj(f), n=2 * n, axis=0)[: limit + 1]
    var = acov[0]
    ok = var > 0
    if not ok.any():
        return 0
    acf = np.mean(acov[:, ok] / var[ok], axis=1)
    below = np.nonzero(acf < GUARD_ACF)[0]
    return int(below[0]) if below.size else int(limit)


def sample_library(X: np.ndarray, Y: np.ndarray, span: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The random sample library of paper 002, eq. 11: s − P* rows from a log of s rows.

    With span P* = `span`, row i of the library (i = 1 … s − P*, here 0 … s − P* − 1) is
    W_i − W_(i+P_i), P_i drawn uniformly from the integers 1 … P*. Every partner i + P_i
    lies inside the log (at most row s), so exactly s − P* rows are kept, none dropped.
    Raises ValueError unless 1 ≤ `span` < s.
    """
    s = X.shape[0]
    if not 1 <= span < s:
        raise ValueError(f"span must be 1..{s - 1} for a log of {s} rows, got {span}")
    i = np.arange(s - span)
    j = i + rng.integers(1, span + 1, size=i.size)
    return X[i] - X[j], Y[i] - Y[j]


def rows_needed(n_components: int, cv_blocks: int | None = None) -> int:
    """Rows a PLS fit (on the log or on its sample library) needs for `n_components` components.

    Leave-one-out (`cv_blocks` None): components + 3, to fit and cross-validate them. Each
    leave-one-out refit has rows − 1 samples, whose centred matrix has rank at most
    rows − 2, and h components need rank h; one more row keeps the last component's
    left-out fit from merely interpolating its data, so its Q² still means something.
    Blocked over `cv_blocks` equal stretches: enough rows that holding out the longest
    stretch (one row at least) still leaves components + 3 to fit.
    """
    need = n_components + 3
    if cv_blocks is None:
        return need
    n = max(need, cv_blocks)
    while train_rows(n, equal_blocks(n, cv_blocks), 0).min() < need:
        n += 1
    return n


@dataclass
class BlockedDesign:
    """How blocked cross-validation cuts the fit rows: the held-out blocks, how they were cut, the guard band."""

    blocks: list[tuple[int, int]]
    split: str  # "equal" or "gaps"
    guard_rows: int
    guard: str  # how its width was set: option, autocorrelation, half a block, library_span, none


def blocked_design(
    t_s: np.ndarray,
    R: np.ndarray,
    Y: np.ndarray,
    n_fit: int,
    n_components: int,
    opt: Options,
    file: str,
    levels: list[list[tuple[int, int]]] | None = None,
) -> BlockedDesign:
    """Blocks and guard band for a fit on the first `n_fit` rows' times (the log's rows or its library's).

    Guard band (`cv_guard_rows`, default from the data): rows next to a held-out stretch
    carry nearly its noise, so they are left out of the fit that predicts it. Its width is
    where the autocorrelation of the residuals of a one-component fit to the log falls
    below 0.05 (`guard_rows_from_residuals`; one component leaves the noise in the
    residual, where more would fit part of it away), at most half a stretch, and never
    so wide that a fit has fewer than `rows_needed` rows. A sample library row reaches
    up to P* logged rows ahead, so the span is added. Stretches cut at gaps need no band
    (their neighbours lie across the gap), only the span.
    """
    need = rows_needed(n_components)
    if levels and opt.library_span is None and opt.cv_guard_rows is None and train_rows(n_fit, levels, 0).min() >= need:
        # the log runs at two or more duty levels: each level held out whole, as an unseen day's duty
        # (compd.identify.holdout.level_folds); their runs are hours long and end in pauses: no guard band
        return BlockedDesign(list(levels), "levels", 0, "none")
    blocks, split = held_out_blocks(t_s[:n_fit], opt.cv_blocks, need)
    span = opt.library_span or 0
    if opt.cv_guard_rows is not None:
        guard, how = opt.cv_guard_rows, "option"
        left = int(train_rows(n_fit, blocks, guard).min())
        if left < need:
            raise BadInput(
                f"a guard band of {guard} rows leaves {left} rows to fit {n_components} components, which need {need};"
                f" at most {max_guard_rows(n_fit, blocks, need)} here",
                file=file,
                path="--option cv_guard_rows",
            )
        return BlockedDesign(blocks, split, guard, how)
    if split == "gaps":
        guard, how = span, "none" if span == 0 else "library_span"
    else:
        cap = n_fit // (2 * len(blocks))
        res = Y - fit_pls(R, Y, 1).predict(R)
        guard = guard_rows_from_residuals(res, cap) + span
        guard, how = (cap, "half a block") if guard >= cap else (guard, "autocorrelation")
    return BlockedDesign(blocks, split, min(guard, max_guard_rows(n_fit, blocks, need)), how)


class Options(Strict):
    """`compd fit --kind lvr --option KEY=VALUE`."""

    max_components: int = Field(10, ge=1, le=100, description="components tried by the selection")
    n_components: int | None = Field(None, ge=1, description="force this many; no selection (Q² still reported)")
    selection: Literal["blocked", "loo"] = Field(
        "blocked",
        description="how components are chosen: blocked = cross-validation over stretches of the log held out"
        " whole (compd's form: a 1 Hz log's neighbouring rows share their noise); loo = leave-one-out Q² (paper 002)",
    )
    q2_limit: float = Field(
        Q2_LIMIT,
        le=1.0,
        description="loo: keep component h while Q²_h ≥ this; blocked: the fewest components that no larger count"
        " improves by this (1 − its held-out PRESS over theirs)",
    )
    cv_blocks: int = Field(
        5, ge=2, le=50, description="blocked: stretches of equal length held out in turn (a log with gaps: its days)"
    )
    cv_guard_rows: int | None = Field(
        None,
        ge=0,
        description="blocked: rows each side of a held-out stretch left out of its fit; none = from the"
        " residuals' autocorrelation",
    )
    library_span: int | None = Field(
        None, ge=1, description="sample library span P* (eq. 11: keeps s − P* of s rows); none = off"
    )
    seed: int = Field(0, description="random seed of the sample library")


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """Fit PLS on rises (optionally on the sample library), components chosen by blocked CV or LOO Q²."""
    opt = validate_options("lvr", Options, options)
    inputs, targets, X, Y = linear_data(log, inputs, targets)
    ok = measured_rows(Y)  # PLS has no memory: the rows without a measured error simply drop out
    R, Y, t_s = rises(X)[ok], Y[ok], log.t_s[ok]
    p = len(inputs)
    want = opt.n_components or opt.max_components
    if want > p:
        if opt.n_components is not None:
            raise BadInput(f"n_components {want} exceeds the {p} inputs", path="--option n_components")
        want = p
    blocked = opt.selection == "blocked"
    need = rows_needed(want, opt.cv_blocks if blocked else None)
    what = f"lvr with {want} components" + (f" and {opt.cv_blocks} cross-validation blocks" if blocked else "")
    if opt.library_span is not None:
        s, span = R.shape[0], opt.library_span
        require_rows(log, s, need + 1, f"a sample library for {what}")
        if s - span < need:
            raise BadInput(
                f"span {span} keeps {max(s - span, 0)} of the log's {s} rows (eq. 11: s − P*); "
                f"{what} needs at least {need}: use a span of at most {s - need}",
                file=log.file,
                path="--option library_span",
            )
        R_fit, Y_fit = sample_library(R, Y, span, np.random.default_rng(opt.seed))
    else:
        R_fit, Y_fit = R, Y
    require_rows(log, R_fit.shape[0], need, what)
    t0 = time.perf_counter()
    design = None
    try:
        if blocked:
            levels = [holdout.on_rows(f, ok) for f in holdout.level_folds(log)] or None
            design = blocked_design(t_s, R, Y, R_fit.shape[0], want, opt, log.file, levels)
            n_comp, q2, press = select_blocked(R_fit, Y_fit, want, design.blocks, design.guard_rows, opt.q2_limit)
            press_h = press[1:].tolist()
        else:
            n_comp, q2, full = select_components(R_fit, Y_fit, want, opt.q2_limit)
            press_h = [float((1.0 - q2[h]) * full.ss_[h]) for h in range(want)]
        n_comp = opt.n_components or n_comp
        pls = fit_pls(R_fit, Y_fit, n_comp)
    except ValueError as e:
        raise BadInput(f"PLS cannot use these inputs: {e}", file=log.file) from None
    fit_s = time.perf_counter() - t0
    intercept = pls.intercept_
    if opt.library_span is not None:  # differences carry no offset: take it from the log
        intercept = np.mean(Y - R @ pls.coef_, axis=0)
    params = LVRParams(
        coef_um_per_k=pls.coef_.tolist(),
        intercept_um=np.atleast_1d(intercept).tolist(),
        t0_c=None,
        n_components=n_comp,
        **rise_stats(R),
    )
    axes = axis_names(targets)
    model = LVR(params, inputs, axes)
    report: dict[str, Any] = {
        "selection": opt.selection,
        "n_components": n_comp,
        "q2": q2,
        "press": press_h,
        "q2_limit": opt.q2_limit,
    }
    if design is not None:
        report["cv"] = {
            "split": design.split,
            "blocks": [
                [[lo, hi - 1] for lo, hi in _block_ranges(b)] if isinstance(b, list) else [b[0], b[1] - 1]
                for b in design.blocks
            ],
            "guard_rows": design.guard_rows,
            "guard": design.guard,
            "press_0": float(press[0]),
        }
    report |= {
        "fit_rows": int(R_fit.shape[0]),
        "library_span": opt.library_span,
        "pls_cv_s": fit_s,
        "influence": {
            name: dict(zip(axes, map(float, pls.coef_std_[j]), strict=True)) for j, name in enumerate(inputs)
        },
    }
    report["at_bounds"] = []
    if opt.n_components is None and n_comp == want < p:
        report["at_bounds"].append(f"{n_comp} components, the most tried (max_components): more might predict better")
    if q2 and q2[0] < opt.q2_limit:
        report["warning"] = (
            f"even the first component has Q² {q2[0]:.3f} < {opt.q2_limit}: the inputs predict the error poorly"
        )
    return FitResult(model, report)


def choices(result: FitResult) -> dict[str, Any]:
    """What this fit chose beyond its coefficients, as options (compd.identify.lag holds them): the components."""
    return {"n_components": int(result.model.params.n_components)}

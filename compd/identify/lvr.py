"""Identification of the LVR model: PLS on temperature rises, components by exact fast LOO Q² (paper 002).

The fit standardises X (n × p rises) and Y (n × q errors) with the sample standard
deviation, extracts components by the paper's algorithm (w_h the dominant eigenvector
of E'F F'E, t_h = E w_h, p_h = E't_h/‖t_h‖², r_h = F't_h/‖t_h‖², deflate E and F),
and maps F0 = E0 B back to original units. Components are kept while the leave-one-out
Q²_h = 1 − PRESS_h / SS_(h−1) ≥ 0.0975 (= 1 − 0.95²).

Exact leave-one-out without n refits: with the data centred on the full mean, the
left-out set's centred cross products are X'X − (1 + 1/m) x_i x_i' and
X'Y − (1 + 1/m) x_i y_i' (m = n − 1), its standard deviations follow from their
diagonals, and a kernel PLS (Dayal & MacGregor 1997, algorithm 1: deflate only X'Y)
on those p × p and p × q matrices gives the same components as NIPALS on the
left-out data. All n problems are solved at once as stacked arrays: O(n p² h).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field

from compd.config import Strict
from compd.errors import BadInput
from compd.identify.data import FitResult, axis_names, require_rows, validate_options
from compd.identify.mlr import linear_data, rise_stats, rises
from compd.log import Log
from compd.models.lvr import LVR, LVRParams

Q2_LIMIT = 0.0975  # 1 − 0.95² (paper 002)


@dataclass
class PLSModel:
    """A fitted PLS regression: `coef_` (p × q, original units), `intercept_` (q)."""

    coef_: np.ndarray
    intercept_: np.ndarray
    coef_std_: np.ndarray  # p × q in standardised units (the paper's influence chart)
    x_mean_: np.ndarray
    x_std_: np.ndarray
    y_mean_: np.ndarray
    y_std_: np.ndarray
    x_weights_: np.ndarray  # p × h, w_h
    x_loadings_: np.ndarray  # p × h, p_h
    y_loadings_: np.ndarray  # q × h, r_h
    x_scores_: np.ndarray  # n × h, t_h
    ss_: np.ndarray  # h + 1: residual sum of squares of standardised Y after 0..h components

    @property
    def n_components(self) -> int:
        return self.x_weights_.shape[1]

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Ŷ = X B + b0, shape (n, q)."""
        return np.asarray(X, dtype=float) @ self.coef_ + self.intercept_


def _standardise(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mean = A.mean(axis=0)
    std = A.std(axis=0, ddof=1)
    std[std == 0.0] = 1.0
    return (A - mean) / std, mean, std


def _dominant_left_vector(M: np.ndarray) -> np.ndarray:
    """Unit eigenvector of M M' for its largest eigenvalue (M is p × q)."""
    if M.shape[1] == 1:
        w = M[:, 0].copy()
    else:
        u, _, _ = np.linalg.svd(M, full_matrices=False)
        w = u[:, 0].copy()
    return w / np.linalg.norm(w)


def _as_xy(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """X (n × p) and Y as float arrays, Y as n × q; returns X, Y, n, p, q."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if Y.ndim == 1:
        Y = Y[:, None]
    return X, Y, X.shape[0], X.shape[1], Y.shape[1]


def fit_pls(X: np.ndarray, Y: np.ndarray, n_components: int) -> PLSModel:
    """PLS regression by the paper's algorithm (paper 002, eqs. 3–8), `n_components` components.

    X: n × p, Y: n × q (or n). Returns coefficients in original units, equal to
    scikit-learn's PLSRegression(scale=True) when its power iteration has converged.
    """
    X, Y, n, p, q = _as_xy(X, Y)
    if Y.shape[0] != n:
        raise ValueError(f"X has {n} rows, Y has {Y.shape[0]}")
    if not 1 <= n_components <= min(n - 1, p):
        raise ValueError(f"n_components must be 1..{min(n - 1, p)}, got {n_components}")
    E, x_mean, x_std = _standardise(X)
    F, y_mean, y_std = _standardise(Y)
    W = np.zeros((p, n_components))
    P = np.zeros((p, n_components))
    Rl = np.zeros((q, n_components))
    T = np.zeros((n, n_components))
    ss = np.zeros(n_components + 1)
    ss[0] = float(np.sum(F * F))
    for h in range(n_components):
        w = _dominant_left_vector(E.T @ F)
        t = E @ w
        tt = float(t @ t)
        if tt <= 1e-12 * n:
            raise ValueError(f"component {h + 1} has no variance left in X (rank {h})")
        p_h = E.T @ t / tt
        r_h = F.T @ t / tt
        E -= np.outer(t, p_h)
        F -= np.outer(t, r_h)
        W[:, h], P[:, h], Rl[:, h], T[:, h] = w, p_h, r_h, t
        ss[h + 1] = float(np.sum(F * F))
    rot = W @ np.linalg.inv(P.T @ W)
    B_std = rot @ Rl.T
    coef = B_std * y_std[None, :] / x_std[:, None]
    intercept = y_mean - x_mean @ coef
    return PLSModel(coef, intercept, B_std, x_mean, x_std, y_mean, y_std, W, P, Rl, T, ss)


def loo_press(X: np.ndarray, Y: np.ndarray, max_components: int, chunk_elems: int = 4_000_000) -> np.ndarray:
    """Exact leave-one-out PRESS_h, h = 1..max_components, in full-data standardised Y units.

    Each left-out fit re-standardises on its own n − 1 rows, as a naive refit does.
    See the module docstring for the downdate; samples are processed in chunks of
    about `chunk_elems` / p² at a time to bound memory.
    """
    X, Y, n, p, q = _as_xy(X, Y)
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


def sample_library(
    X: np.ndarray, Y: np.ndarray, span: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
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


def rows_needed(n_components: int) -> int:
    """Rows a PLS fit (on the log or on its sample library) needs for `n_components` components.

    Components + 3, to fit and cross-validate them. Each leave-one-out refit
    has rows − 1 samples, whose centred matrix has rank at most rows − 2, and h
    components need rank h; one more row keeps the last component's left-out fit from
    merely interpolating its data, so its Q² still means something.
    """
    return n_components + 3


class Options(Strict):
    """`compd fit --kind lvr --option KEY=VALUE`."""

    max_components: int = Field(10, ge=1, le=100, description="components tried by Q² selection")
    n_components: int | None = Field(None, ge=1, description="force this many; no Q² selection")
    q2_limit: float = Field(Q2_LIMIT, description="keep component h while Q²_h ≥ this")
    library_span: int | None = Field(
        None, ge=1, description="sample library span P* (eq. 11: keeps s − P* of s rows); none = off"
    )
    seed: int = Field(0, description="random seed of the sample library")


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """Fit PLS on rises (optionally on the sample library), components chosen by LOO Q²."""
    opt = validate_options("lvr", Options, options)
    inputs, targets, X, Y = linear_data(log, inputs, targets)
    R = rises(X)
    p = len(inputs)
    want = opt.n_components or opt.max_components
    if want > p:
        if opt.n_components is not None:
            raise BadInput(f"n_components {want} exceeds the {p} inputs", path="--option n_components")
        want = p
    if opt.library_span is not None:
        s, span, need = R.shape[0], opt.library_span, rows_needed(want)
        require_rows(log, s, need + 1, f"a sample library for lvr with {want} components")
        if s - span < need:
            raise BadInput(
                f"span {span} keeps {max(s - span, 0)} of the log's {s} rows (eq. 11: s − P*); "
                f"lvr with {want} components needs at least {need}: use a span of at most {s - need}",
                file=log.file,
                path="--option library_span",
            )
        R_fit, Y_fit = sample_library(R, Y, span, np.random.default_rng(opt.seed))
    else:
        R_fit, Y_fit = R, Y
    require_rows(log, R_fit.shape[0], rows_needed(want), f"lvr with {want} components")
    t0 = time.perf_counter()
    if opt.n_components is not None:
        n_comp = opt.n_components
        pls = fit_pls(R_fit, Y_fit, n_comp)
        press = loo_press(R_fit, Y_fit, n_comp)
        q2 = [float(1.0 - press[h] / pls.ss_[h]) for h in range(n_comp)]
    else:
        try:
            n_comp, q2, _ = select_components(R_fit, Y_fit, want, opt.q2_limit)
        except ValueError as e:
            raise BadInput(f"PLS cannot use these inputs: {e}", file=log.file) from None
        pls = fit_pls(R_fit, Y_fit, n_comp)
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
    report = {
        "n_components": n_comp,
        "q2": q2,
        "q2_limit": opt.q2_limit,
        "fit_rows": int(R_fit.shape[0]),
        "library_span": opt.library_span,
        "pls_loo_s": fit_s,
        "influence": {
            name: dict(zip(axes, map(float, pls.coef_std_[j]), strict=True))
            for j, name in enumerate(inputs)
        },
    }
    if q2 and q2[0] < opt.q2_limit:
        report["warning"] = (
            f"even the first component has Q² {q2[0]:.3f} < {opt.q2_limit}: "
            "the inputs predict the error poorly"
        )
    return FitResult(model, report)

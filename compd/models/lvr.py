"""Latent-variable regression (PLS) on temperature rises (paper 002): the model and the PLS regression it comes from.

`fit_pls` is the paper's algorithm: it standardises X (n × p rises) and Y (n × q errors)
with the sample standard deviation, extracts components (w_h the dominant eigenvector of
E'F F'E, t_h = E w_h, p_h = E't_h/‖t_h‖², r_h = F't_h/‖t_h‖², deflate E and F) and maps
F0 = E0 B back to original units. It is plain numpy with no fitting workflow, so both
the identification (compd.identify.lvr: how many components, by blocked cross-validation
or the paper's LOO Q², from a log) and outside callers use it from here. The fitted model
evaluates the same linear form as MLR (compd.models.mlr.RiseLinear).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from compd.core.errors import BadInput
from compd.models.mlr import RiseLinear, RiseLinearParams


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


def as_xy(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int, int]:
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
    X, Y, n, p, q = as_xy(X, Y)
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


class LVRParams(RiseLinearParams):
    """LVR run-time params: the linear form plus how many components it was built from."""

    n_components: int = Field(ge=1, description="PLS components the coefficients come from (≤ inputs)")


class LVR(RiseLinear):
    """PLS model on temperature rises (paper 002)."""

    kind = "lvr"
    summary_keys = ("n_components", "coef_um_per_k", "intercept_um")
    per_axis_keys = ("intercept_um",)
    Params = LVRParams
    params: LVRParams

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        if params.n_components > len(inputs):
            raise BadInput(
                f"{params.n_components} components from {len(inputs)} inputs: at most one per input",
                path=("params", "n_components"),
            )

"""The AR(1) fit's least squares prepared once per log.

Its columns at every candidate C1, each fold's Gram blocks, bounded solves in batches.

compd.identify.ar1 chooses its sensors, its C1 form and the lag by the held-out error of many
candidates (compd.identify.holdout's folds). Refitting the model per candidate per fold is
what made those fits take minutes; here the work is shared:

* the log is taken at the model's steps once (`prepare`): the target, the speed, every
  temperature column's rise from the first step, C2's columns, and per fold the steps its
  fit counts and the logged rows it is scored on;
* for each C1 of a grid (the paper's one C1, or the speed law's C1 at standstill and its
  growth with speed) every candidate column is filtered once, and every fold's Gram blocks
  come from one pass over the steps (`Scan`); a candidate set of sensors is a sub-block of
  those, so its least squares at every grid point in every fold is one batch of small
  bounded solves (`bounded_lstsq`);
* a fold's C1 is the grid's best, refined by a parabola through it and its neighbours
  (`quick`, for ranking many candidates) or by the bounded search the fit makes on the whole
  log (`exact`, for the figures a report gives);
* C2 is a table on the speed levels (monotone: increments ≥ 0) or, for a log at many
  speeds, C2(n) = c1 (n/n_ref) + c2 (n/n_ref)² (both ≥ 0). A level a fold hides keeps its node,
  tied to its neighbours by the table's own rule (linear between levels, the exponent beyond
  the ends), which is what a fit on the fold's own levels gives there: the columns are the
  same for every fold and are filtered once;
* compd's C1 per level searches its few parameters per fold by Nelder–Mead, each evaluation
  one filter of the columns the candidate uses (`filter_rows`: in blocks, no loop per step).

A fold's prediction is the fitted model run over every row from a cold start (S(0) = 0, the
rises from the first step), held between steps, as compd.identify.holdout scores it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, signal

from compd.identify import holdout
from compd.identify.data import measured_rows
from compd.log import Log
from compd.models.base import step_rows

RIDGE = 1e-11  # added to the unit diagonal of a scaled Gram: a column without variance solves to 0
BLOCK_ROWS = 512  # rows per block of filter_rows: C1 ≥ e^(−1/2) keeps the products above 1e-111

# The spindle's time constant τ = −Δτ / ln C1 is searched from two steps to a day: a rod that
# takes longer than a day to follow its heat is no spindle (the fit would be an integrator, the
# bed gains taking up what it cannot), one faster than two steps has no memory at this Δτ.
TAU_MIN_STEPS = 2.0
TAU_MAX_S = 86400.0
GRID_POINTS = 40  # the fit's C1 grid (then a bounded search between the best point's neighbours)
SCAN_POINTS = 90  # the selection's C1 grid (then a parabola): within 1.5 % of the bounded search
LAW_RATIOS = (
    1.0,
    1.25,
    1.6,
    2.0,
    2.5,
    3.2,
    4.0,
    5.0,
    6.5,
    8.0,
)  # the speed law's grid of ρ: cooling at n_ref / at rest
RATE_RATIO_MAX = 50.0  # ρ at most
LAW_Z_POINTS = 30  # the speed law's grid of C1 at standstill


def c1_grid(dt_s: float, points: int = GRID_POINTS) -> np.ndarray:
    """z = log(1 − C1) on a grid from τ = TAU_MIN_STEPS Δτ to max(TAU_MAX_S, 50 Δτ), even in z."""
    tau_lo, tau_hi = TAU_MIN_STEPS * dt_s, max(TAU_MAX_S, 50.0 * dt_s)
    return np.linspace(np.log(-np.expm1(-dt_s / tau_lo)), np.log(-np.expm1(-dt_s / tau_hi)), points)


def b_of_z(z: np.ndarray | float) -> np.ndarray | float:
    """b = −ln C1 (per step) of z = log(1 − C1)."""
    return -np.log1p(-np.exp(z))


def c2_basis(speed_rpm: np.ndarray, rpm: Sequence[float], exponent: float | None) -> np.ndarray:
    """Rows × levels: C2(n_k) = basis[k] @ c for the node values c, as compd.models.ar1.c2_of_speed
    gives it (linear between the nodes; beyond them the power law of `exponent`, or for None linear
    from (0, 0) below the first and held past the last)."""
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    r = np.asarray(rpm, dtype=float)
    L = r.size
    W = np.zeros((n.size, L))
    if L == 0:
        return W
    j = np.searchsorted(r, n, side="left")  # the first node at or above the speed
    k = np.arange(n.size)
    first = j == 0
    W[k[first], 0] = n[first] / r[0]
    mid = (j > 0) & (j < L)
    lo = j[mid] - 1
    frac = (n[mid] - r[lo]) / (r[lo + 1] - r[lo])
    W[k[mid], lo] = 1.0 - frac
    W[k[mid], lo + 1] = frac
    W[k[j == L], L - 1] = 1.0
    if exponent is not None:
        below, above = n <= r[0], (n >= r[-1]) & (n > r[0])
        W[below] = 0.0
        W[below, 0] = (n[below] / r[0]) ** exponent
        W[above] = 0.0
        W[above, L - 1] = (n[above] / r[-1]) ** exponent
    return W


def filter_rows(c1: np.ndarray, U: np.ndarray, s0: float = 0.0) -> np.ndarray:
    """s(k) = C1(k) s(k−1) + u(k) from s(−1) = s0 for one C1 per row, column-wise: in blocks of
    BLOCK_ROWS rows, s = P (s_start + cumsum(u / P)) with P the running product of C1 in the block
    (the rounding of the step-by-step loop to ~1e-13; C1 ≥ e^(−1/2) keeps P ≥ 1e-111)."""
    U = np.asarray(U, dtype=float)
    out = np.empty_like(U)
    prev = np.full(U.shape[1:], s0, dtype=float)
    logc = np.log(np.asarray(c1, dtype=float))
    for lo in range(0, U.shape[0], BLOCK_ROWS):
        hi = min(lo + BLOCK_ROWS, U.shape[0])
        p = np.exp(np.cumsum(logc[lo:hi]))
        if U.ndim == 2:
            p = p[:, None]
        block = p * (prev + np.cumsum(U[lo:hi] / p, axis=0))
        out[lo:hi] = block
        prev = block[-1]
    return out


def filter_c1(c1: float | np.ndarray, U: np.ndarray) -> np.ndarray:
    """s(k) = C1 s(k−1) + u(k) from 0, column-wise: scipy's lfilter for one C1, `filter_rows` for one per row."""
    if np.ndim(c1) == 0:
        return signal.lfilter([1.0], [1.0, -float(c1)], U, axis=0)
    return filter_rows(np.asarray(c1), U)


def _masked_solve(G: np.ndarray, g: np.ndarray, passive: np.ndarray) -> np.ndarray:
    """Per problem, the solution of G x = g on its passive variables, 0 on the others."""
    both = passive[:, :, None] & passive[:, None, :]
    eye = np.eye(G.shape[-1], dtype=bool)[None]
    A = np.where(both, G, 0.0) + (eye & ~both)
    return np.linalg.solve(A, np.where(passive, g, 0.0)[..., None])[..., 0]


def bounded_lstsq(G: np.ndarray, g: np.ndarray, lower: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """min ‖A x − b‖² for a batch of problems given as G = A'A (…, k, k) and g = A'b (…, k), with
    x_j ≥ 0 where `lower[j]` and free elsewhere (`lower` broadcast to g's shape). `start`, the
    solution of a problem close by (the same columns at a C1 close by), starts the active set.

    Columns are scaled to unit norm (RIDGE keeps a column without variance at 0). Each problem
    starts from its unconstrained solution (or from `start`'s variables off their bounds), drops
    the bounded variables that come out negative until the rest is feasible, then runs Lawson
    and Hanson's active set from there (release the bound variable whose gradient is largest,
    step back to feasibility, repeat): few solves where few bounds hold, every problem of the
    batch a step at a time."""
    shape = g.shape
    k = shape[-1]
    G = G.reshape(-1, k, k)
    g = g.reshape(-1, k)
    m = g.shape[0]
    diag = np.sqrt(np.maximum(np.diagonal(G, axis1=1, axis2=2), 0.0))
    d = 1.0 / np.where(diag > 0, diag, 1.0)
    Gs = G * d[:, :, None] * d[:, None, :] + RIDGE * np.eye(k)
    gs = g * d
    lower = np.broadcast_to(np.asarray(lower, dtype=bool), shape).reshape(m, k)
    passive = np.ones((m, k), dtype=bool) if start is None else ~lower | (start.reshape(m, k) > 0)
    x = np.zeros((m, k))
    live = np.arange(m)
    for _ in range(k + 1):  # feasibility: drop the bounded variables that come out negative
        s = _masked_solve(Gs[live], gs[live], passive[live])
        neg = lower[live] & passive[live] & (s < 0.0)
        bad = neg.any(axis=1)
        x[live[~bad]] = s[~bad]
        if not bad.any():
            break
        live = live[bad]
        p = passive[live]
        p[neg[bad]] = False
        passive[live] = p
    tol = 1e-12 * np.maximum(np.abs(gs).max(axis=1, initial=0.0), 1e-300)
    for _ in range(3 * k + 3):  # Lawson–Hanson from the feasible point
        w = gs - (Gs @ x[:, :, None])[:, :, 0]
        enter = lower & ~passive & (w > tol[:, None])
        rows = np.flatnonzero(enter.any(axis=1))
        if rows.size == 0:
            break
        j = np.argmax(np.where(enter[rows], w[rows], -np.inf), axis=1)
        passive[rows, j] = True
        live = rows
        for _ in range(k + 1):  # step back until the passive set is feasible
            s = _masked_solve(Gs[live], gs[live], passive[live])
            neg = lower[live] & passive[live] & (s <= 0.0)
            bad = neg.any(axis=1)
            x[live[~bad]] = s[~bad]
            if not bad.any():
                break
            live, s, neg = live[bad], s[bad], neg[bad]
            xl = x[live]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(neg, xl / (xl - s), np.inf)
            alpha = np.clip(ratio.min(axis=1), 0.0, 1.0)
            xl = xl + alpha[:, None] * (s - xl)
            out = lower[live] & passive[live] & (xl <= 1e-14 * np.abs(xl).max(axis=1, keepdims=True) + 1e-300)
            out[np.arange(live.size), np.argmin(ratio, axis=1)] = True  # the one that stopped the step leaves
            xl[out] = 0.0
            x[live] = xl
            p = passive[live]
            p[out] = False
            passive[live] = p
    return (x * d).reshape(shape)


def sse(G: np.ndarray, g: np.ndarray, c: np.ndarray | float, x: np.ndarray) -> np.ndarray:
    """‖A x − b‖² = b'b − 2 x'g + x'G x, over a batch (c = b'b)."""
    return c - 2.0 * np.sum(x * g, axis=-1) + (x[..., None, :] @ G @ x[..., :, None])[..., 0, 0]


@dataclass
class FoldRows:
    """One fold at the model's steps: the steps its fit counts (`train`) and the logged rows it is
    scored on, as the steps their held prediction comes from (`held_steps`), with the count, sum
    and sum of squares of the logged error per such step; `nodes` the levels it has training rows at."""

    train: np.ndarray  # bool per step
    held_steps: np.ndarray
    held_count: np.ndarray
    held_sum: np.ndarray
    held_sq: float
    rows: int  # logged rows scored
    nodes: np.ndarray
    why: str = ""  # why the fold cannot be fitted ("" if it can)


@dataclass
class Steps:
    """A log at the model's steps (Δτ), prepared once for every candidate's least squares.

    `rise` holds the columns `names` as their rise from the first step; `W` is C2's columns:
    the table's basis on the full log's `levels` (`law` False) or (n/n_ref, (n/n_ref)²) (`law`
    True), row 0 zero (ΔL(0) = 0). `full` is the fit on every measured step, `folds` the held-out
    folds."""

    dt_s: float
    rows: np.ndarray
    E: np.ndarray
    speed: np.ndarray
    names: list[str]
    rise: np.ndarray
    levels: list[float]
    exponent: float | None
    law: bool
    W: np.ndarray
    full: FoldRows
    folds: list[FoldRows] = field(default_factory=list)

    def column(self, name: str) -> np.ndarray:
        return self.rise[:, self.names.index(name)]

    def only(self, names: Sequence[str]) -> Steps:
        """The same steps with the columns `names` alone (a scan of one candidate's sensors)."""
        rise = np.column_stack([self.column(n) for n in names]) if names else np.zeros((self.rows.size, 0))
        return Steps(
            self.dt_s,
            self.rows,
            self.E,
            self.speed,
            list(names),
            rise,
            self.levels,
            self.exponent,
            self.law,
            self.W,
            self.full,
            self.folds,
        )

    def c2_map(self, fold: FoldRows) -> np.ndarray:
        """Columns of W → the fold's C2 coefficients (each ≥ 0): the monotone increments over the
        levels it has rows at (a hidden level tied to its neighbours: `tie_map`), or the law's two."""
        if self.law:
            return np.eye(2) if fold.nodes.size else np.zeros((2, 0))
        r = np.asarray(self.levels, dtype=float)
        tie = c2_basis(r, r[fold.nodes], self.exponent) if fold.nodes.size else np.zeros((r.size, 0))
        return tie @ np.tril(np.ones((fold.nodes.size, fold.nodes.size)))

    def each(self, folds: bool) -> list[tuple[int, FoldRows]]:
        """(index, rows) of the held-out folds (1 …), or of the whole log (0)."""
        return [(k + 1, f) for k, f in enumerate(self.folds)] if folds else [(0, self.full)]


def speed_levels_rpm(moving_rpm: np.ndarray, round_rpm: float) -> list[float]:
    """The logged speed levels: sorted speeds closer than `round_rpm` to the previous one join its level."""
    return level_labels(np.asarray(moving_rpm, float), np.ones(np.size(moving_rpm), bool), round_rpm)[0]


def level_labels(speed: np.ndarray, use: np.ndarray, round_rpm: float) -> tuple[list[float], np.ndarray]:
    """The speed levels of the steps in `use` (`speed_levels_rpm`), and per step its level (−1 outside)."""
    label = np.full(speed.size, -1, dtype=np.intp)
    idx = np.flatnonzero(use)
    if idx.size == 0:
        return [], label
    order = idx[np.argsort(speed[idx], kind="stable")]
    v = speed[order]
    group = np.r_[0, np.cumsum(np.diff(v) > round_rpm)]
    label[order] = group
    levels = [float(np.mean(v[group == g])) for g in range(int(group[-1]) + 1)]
    return levels, label


def prepare(
    log: Log,
    target: str,
    names: Sequence[str],
    speed_column: str,
    dt_s: float,
    round_rpm: float,
    stopped_rpm: float,
    exponent: float | None,
    cut: list[holdout.Fold] | None,
    law: bool = False,
) -> Steps:
    """`Steps` of `log` for the target, the speed and the temperature columns `names` (each finite in
    every row), with the held-out folds `cut` (log rows; None: none). `law`: C2's columns are the
    speed law's, n_ref the fastest level."""
    t = log.t_s
    rows = step_rows(t, dt_s)
    X = log.matrix([speed_column, *names])[rows]
    Y = log.col(target)
    E = Y[rows]
    speed = np.abs(X[:, 0])
    rise = X[:, 1:] - X[0, 1:]
    measured = measured_rows(E)
    moving = speed >= max(stopped_rpm, 1e-12)
    levels, level_of = level_labels(speed, moving & measured, round_rpm)
    if law and levels:
        x = speed / levels[-1]
        W = np.column_stack([x, x * x])
    else:
        W = c2_basis(speed, levels, exponent)
    W[0] = 0.0  # ΔL(0) = 0 (paper 001, eq. 17): C2 enters from the second step on
    idx = np.searchsorted(rows, np.arange(len(log)), side="right") - 1  # log row → the step it holds

    def fold_rows(hidden: np.ndarray | None, k: int) -> FoldRows:
        train = measured.copy()
        held = np.zeros(0, dtype=np.intp)
        if hidden is not None:
            train &= ~hidden[rows]
            held = np.flatnonzero(hidden & np.isfinite(Y))
        steps, inverse = np.unique(idx[held], return_inverse=True)
        count = np.bincount(inverse, minlength=steps.size).astype(float)
        total = np.bincount(inverse, weights=Y[held], minlength=steps.size)
        nodes = np.unique(level_of[train & (level_of >= 0)])
        why = ""
        if hidden is not None and held.size == 0:
            why = f"fold {k}: no measured error"
        elif nodes.size == 0:
            why = (f"fold {k}: " if hidden is not None else "") + f"the spindle never turns in {speed_column!r}"
        return FoldRows(train, steps, count, total, float(np.sum(Y[held] ** 2)), int(held.size), nodes, why)

    steps = Steps(
        dt_s, rows, E, speed, list(names), rise, levels, exponent, bool(law and levels), W, fold_rows(None, 0)
    )
    for k, fold in enumerate(cut or [], start=1):
        hidden = np.zeros(len(log), dtype=bool)
        for lo, hi in fold:
            hidden[lo:hi] = True
        steps.folds.append(fold_rows(hidden, k))
    return steps


@dataclass(frozen=True)
class Roles:
    """A candidate's columns by role: structure sensors (their rise enters the error, ≥ 0 with
    `positive`), the ambient (in the recursion, either sign) and exchange sensors (in the recursion,
    ≥ 0); `sign` the spindle's sign in the error."""

    bed: tuple[str, ...] = ()
    ambient: str | None = None
    exchange: tuple[str, ...] = ()
    sign: int = -1
    positive: bool = True

    @property
    def recursion(self) -> tuple[str, ...]:
        return ((self.ambient,) if self.ambient else ()) + self.exchange

    @property
    def sensors(self) -> tuple[str, ...]:
        return self.bed + self.recursion

    def lower(self, n_c2: int) -> np.ndarray:
        """Per coefficient [C2's, structure, ambient, exchange], whether it is ≥ 0."""
        return np.r_[
            np.ones(n_c2, bool),
            np.full(len(self.bed), self.positive),
            np.zeros(int(self.ambient is not None), bool),
            np.ones(len(self.exchange), bool),
        ]

    def nparam(self, n_c2: int) -> int:
        return n_c2 + len(self.bed) + len(self.recursion)


FoldScore = holdout.FoldScore


class Scan:
    """Every fold's Gram blocks at every C1 of a grid (`c1s`: one C1 each, or one per step each), for
    all the temperature columns of `steps` at once: C2's columns, then each temperature's rise (as a
    structure sensor), then each rise filtered (as a recursion input). A candidate's least squares
    is a sub-block of these (`blocks`)."""

    def __init__(self, steps: Steps, c1s: Sequence[float | np.ndarray], folds: bool = True) -> None:
        self.steps = steps
        self.folds = steps.each(folds)
        Lw, T = steps.W.shape[1], len(steps.names)
        self.Lw, self.T = Lw, T
        U = np.hstack([steps.W, steps.rise])
        nf, k, ng = len(self.folds), Lw + 2 * T, len(c1s)
        self.train_G, self.train_g = np.empty((nf, ng, k, k)), np.empty((nf, ng, k))
        self.held_G, self.held_g = np.empty((nf, ng, k, k)), np.empty((nf, ng, k))
        E = np.where(np.isfinite(steps.E), steps.E, 0.0)
        self.train_c = np.array([float(np.sum(E[f.train] ** 2)) for _, f in self.folds])
        self.held_c = np.array([f.held_sq for _, f in self.folds])
        self._c2: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        full = steps.full.train
        gone = [np.flatnonzero(full & ~f.train) for _, f in self.folds]  # the measured steps each fold hides
        hidden = np.concatenate(gone) if gone else np.zeros(0, dtype=np.intp)
        same = [
            np.array_equal(f.held_steps, g) and bool(np.all(f.held_count == 1))  # held_steps: sorted, unique
            for g, (_, f) in zip(gone, self.folds, strict=True)
        ]
        # the Grams are most of a selection's time: the folds' hidden steps are disjoint, so the whole log's
        # Gram is theirs summed (and the rest's), and a fold held out step by step (one row each) has its
        # hidden steps' Gram as its held-out one
        disjoint = np.unique(hidden).size == hidden.size
        rest = np.setdiff1d(np.flatnonzero(full), hidden)
        for i, c1 in enumerate(c1s):
            F = filter_c1(c1, U)
            A = np.hstack([F[:, :Lw], steps.rise, F[:, Lw:]])
            Ag = [A[g] for g in gone]
            Gs = [a.T @ a for a in Ag]
            if disjoint:
                Ar = A[rest]
                G_all = sum(Gs, Ar.T @ Ar)
            else:
                Am = A[full]
                G_all = Am.T @ Am
            g_all = A[full].T @ E[full]
            for j, (_, f) in enumerate(self.folds):
                self.train_G[j, i] = G_all - Gs[j]
                self.train_g[j, i] = g_all - Ag[j].T @ E[gone[j]]
                if same[j]:
                    self.held_G[j, i] = Gs[j]
                else:
                    Ah = A[f.held_steps]
                    self.held_G[j, i] = (Ah * f.held_count[:, None]).T @ Ah
                self.held_g[j, i] = A[f.held_steps].T @ f.held_sum

    def _c2_part(self, j: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Fold j's C2 rows of its (train, held) Grams mapped to the fold's coefficients, the same for every
        candidate: (C2 × C2, C2 × every column, C2 of g) at every grid C1, made once."""
        if j not in self._c2:
            M = self.steps.c2_map(self.folds[j][1])
            Lw = self.Lw
            self._c2[j] = [
                (M.T @ G[:, :Lw, :Lw] @ M, M.T @ G[:, :Lw], g[:, :Lw] @ M)
                for G, g in ((self.train_G[j], self.train_g[j]), (self.held_G[j], self.held_g[j]))
            ]
        return self._c2[j]

    def blocks(self, roles: Roles, j: int) -> tuple[np.ndarray, ...]:
        """(train G, train g, held G, held g) of `roles` in the scan's fold j at every grid C1, C2's
        columns mapped to the fold's coefficients and the spindle's sign applied."""
        st = self.steps
        Lw, T = self.Lw, self.T
        J = np.array(
            [Lw + st.names.index(n) for n in roles.bed] + [Lw + T + st.names.index(n) for n in roles.recursion],
            dtype=np.intp,
        )
        out = []
        for (G, g), (cc, cx, cg) in zip(
            ((self.train_G[j], self.train_g[j]), (self.held_G[j], self.held_g[j])), self._c2_part(j), strict=True
        ):
            sign = np.r_[
                np.full(cc.shape[-1], float(roles.sign)),
                np.ones(len(roles.bed)),
                np.full(len(roles.recursion), float(roles.sign)),
            ]
            Gcj = cx[:, :, J]
            top = np.concatenate([cc, Gcj], axis=2)
            bottom = np.concatenate([np.swapaxes(Gcj, 1, 2), G[:, J][:, :, J]], axis=2)
            out.append(np.concatenate([top, bottom], axis=1) * sign[None, :, None] * sign[None, None, :])
            out.append(np.concatenate([cg, g[:, J]], axis=1) * sign)
        return tuple(out)

    def solve(self, many: Sequence[Roles], j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For candidates `many` of one size in fold j: (coefficients, train SSE, held-out SSE) at every grid C1."""
        n_c2 = self.steps.c2_map(self.folds[j][1]).shape[1]
        b = [self.blocks(r, j) for r in many]
        G, g = np.stack([x[0] for x in b]), np.stack([x[1] for x in b])
        H, h = np.stack([x[2] for x in b]), np.stack([x[3] for x in b])
        theta = bounded_lstsq(G, g, np.stack([r.lower(n_c2) for r in many])[:, None, :])
        return theta, sse(G, g, self.train_c[j], theta), np.maximum(sse(H, h, self.held_c[j], theta), 0.0)


def _parabola(cost: np.ndarray, values: np.ndarray, i: int) -> float:
    """`values` at the vertex of the parabola through `cost` at grid points i − 1, i, i + 1 (its
    value at i where i is an end or the three do not curve up)."""
    if not 0 < i < cost.size - 1:
        return float(values[i])
    a, b, c = cost[i - 1 : i + 2]
    den = a - 2.0 * b + c
    if den <= 0:
        return float(values[i])
    u = 0.5 * (a - c) / den  # the vertex, in grid steps from i (|u| ≤ 1/2)
    va, vb, vc = values[i - 1 : i + 2]
    return float(vb + 0.5 * u * (vc - va) + 0.5 * u * u * (va - 2.0 * vb + vc))


def _group(many: Sequence[Roles]) -> list[list[int]]:
    groups: dict[int, list[int]] = {}
    for i, r in enumerate(many):
        groups.setdefault(len(r.sensors), []).append(i)
    return list(groups.values())


def too_few(fold: FoldRows, roles: Roles, n_c2: int, k: int) -> str:
    """Why the fold has too few rows for the candidate (as compd.identify.ar1's fit refuses), or ""."""
    have, need = int(fold.train.sum()), roles.nparam(n_c2) + 4
    return f"fold {k}: {have} rows are too few: ar1 needs at least {need}" if have < need else ""


def score_quick(scan: Scan, many: Sequence[Roles], parabola: bool = True) -> list[list[FoldScore]]:
    """Per candidate and fold the held-out (SSE, rows) at the fold's best C1 of the scan's grid, the
    held-out SSE read off the parabola through the best grid point and its neighbours (`_parabola`:
    a 1-D grid of the paper's form; else the best point's): no filter beyond the scan's, for ranking
    many candidates."""
    out: list[list[FoldScore]] = [[] for _ in many]
    for j, (k, fold) in enumerate(scan.folds):
        if fold.why:
            for o in out:
                o.append(fold.why)
            continue
        n_c2 = scan.steps.c2_map(fold).shape[1]
        for members in _group(many):
            _, cost, held = scan.solve([many[i] for i in members], j)
            for m, i in enumerate(members):
                why = too_few(fold, many[i], n_c2, k)
                best = int(np.argmin(cost[m]))
                value = _parabola(cost[m], held[m], best) if parabola else float(held[m][best])
                out[i].append(why or (np.array([max(value, 0.0)]), np.array([fold.rows])))
    return out


@dataclass
class Fitted:
    """One fold's least squares at its C1: the train SSE, the coefficients, the held-out SSE."""

    train_sse: float
    theta: np.ndarray
    held_sse: float


def design(steps: Steps, roles: Roles, c2: np.ndarray, c1: float | np.ndarray) -> np.ndarray:
    """Steps × coefficients at C1 (one, or one per step): [s·filtered C2 columns, structure rises,
    s·filtered recursion rises]."""
    rec = [steps.column(n) for n in roles.recursion]
    F = filter_c1(c1, np.column_stack([c2, *rec]) if rec else c2)
    nc = c2.shape[1]
    cols = [roles.sign * F[:, :nc], *(steps.column(n)[:, None] for n in roles.bed)]
    if rec:
        cols.append(roles.sign * F[:, nc:])
    return np.hstack(cols)


def solve_fold(
    steps: Steps, fold: FoldRows, A: np.ndarray, lower: np.ndarray, start: np.ndarray | None = None
) -> Fitted:
    """The bounded least squares of design `A` on the fold's training steps (`start`: a solution
    close by), and its held-out SSE."""
    At = A[fold.train]
    e = steps.E[fold.train]
    theta = bounded_lstsq(At.T @ At, At.T @ e, lower, start)
    r = At @ theta - e
    p = A[fold.held_steps] @ theta
    held = float(fold.held_count @ (p * p) - 2.0 * (p @ fold.held_sum) + fold.held_sq)
    return Fitted(float(r @ r), theta, max(held, 0.0))


class Search:
    """One fold's least squares as a function of the C1 parameters (z = log(1 − C1), or a form's φ),
    each solve started from the last one's active set."""

    def __init__(
        self,
        steps: Steps,
        roles: Roles,
        fold: FoldRows,
        c1_of: Callable[[np.ndarray], float | np.ndarray],
        c2: np.ndarray,
    ) -> None:
        self.steps, self.roles, self.fold, self.c1_of, self.c2 = steps, roles, fold, c1_of, c2
        self.lower = roles.lower(c2.shape[1])
        self.last: np.ndarray | None = None
        self.calls = 0

    def at(self, phi: np.ndarray) -> Fitted:
        self.calls += 1
        fit = solve_fold(
            self.steps, self.fold, design(self.steps, self.roles, self.c2, self.c1_of(phi)), self.lower, self.last
        )
        self.last = fit.theta
        return fit

    def cost(self, phi: np.ndarray) -> float:
        return self.at(phi).train_sse


def c1_of_z(z: np.ndarray | float) -> float:
    return 1.0 - math.exp(float(np.asarray(z).reshape(-1)[0]))


def score_exact(steps: Steps, roles: Roles, folds: bool = True) -> tuple[list[FoldScore], list[float]]:
    """Per fold (or the whole log) the held-out (SSE, rows) of the paper's form as the fit makes it:
    C1 the best of the fit's grid, then the bounded search between its neighbours (xatol 1e-6 in z);
    and each fold's z."""
    grid = c1_grid(steps.dt_s)
    scan = Scan(steps.only(roles.sensors), 1.0 - np.exp(grid), folds)
    scores: list[FoldScore] = []
    zs: list[float] = []
    for j, (k, fold) in enumerate(scan.folds):
        c2 = steps.W @ steps.c2_map(fold)
        why = fold.why or too_few(fold, roles, c2.shape[1], k)
        if why:
            scores.append(why)
            zs.append(math.nan)
            continue
        _, cost, _ = scan.solve([roles], j)
        cost = cost[0]
        i = int(np.argmin(cost))
        search = Search(steps, roles, fold, c1_of_z, c2)
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = optimize.minimize_scalar(
            lambda z, search=search: search.cost(np.array([z])),
            bounds=(min(lo, hi), max(lo, hi)),
            method="bounded",
            options={"xatol": 1e-6},
        )
        z = float(res.x) if res.fun <= cost[i] else float(grid[i])
        best = search.at(np.array([z]))
        scores.append((np.array([best.held_sse]), np.array([fold.rows])))
        zs.append(z)
    return scores, zs


class LawC1:
    """The speed law's C1 (compd.models.ar1.SpeedLaw, its cooling linear in speed): b = −ln C1 per
    step, b(n) = b0 (1 + (ρ − 1) n/n_ref), φ = (z0 = log(1 − e^(−b0)), γ = ln ρ), b within the grid's
    time constants, ρ ≥ 1 (a turning spindle cools at least as fast as a standing one)."""

    def __init__(self, steps: Steps) -> None:
        self.x = steps.speed / steps.levels[-1] if steps.levels else np.zeros(steps.rows.size)
        grid = c1_grid(steps.dt_s)
        self.z_lo, self.z_hi = float(grid.min()), float(grid.max())
        self.z = np.linspace(self.z_hi, self.z_lo, LAW_Z_POINTS)
        self.b_lo, self.b_hi = float(b_of_z(self.z_lo)), float(b_of_z(self.z_hi))
        self.gamma_max = math.log(RATE_RATIO_MAX)

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        b0 = float(b_of_z(min(max(float(phi[0]), self.z_lo), self.z_hi)))
        ratio = math.exp(min(max(float(phi[1]), 0.0), self.gamma_max))
        return np.exp(-np.clip(b0 * (1.0 + (ratio - 1.0) * self.x), self.b_lo, self.b_hi))

    def grid(self) -> list[np.ndarray]:
        return [np.array([z, math.log(r)]) for z in self.z for r in LAW_RATIOS]


class LevelC1:
    """compd's C1 per level (the model's c1_table): b = −ln C1 at standstill and at each level,
    linear in speed between them and held past the last (compd.models.ar1.c2_of_speed with b at
    standstill at 0). For a fold, φ = z = log(1 − C1) at standstill and at the levels it has rows
    at; a level it hides takes its b from its neighbours by that rule."""

    def __init__(self, steps: Steps, fold: FoldRows) -> None:
        r = np.asarray(steps.levels, dtype=float)
        W1 = c2_basis(steps.speed, r, None)
        tie = c2_basis(r, r[fold.nodes], None)
        # b per step = w0 b(0) + W1 (tie b(nodes) + t0 b(0))
        self.rows = W1 @ tie
        self.rows0 = (1.0 - W1.sum(axis=1)) + W1 @ (1.0 - tie.sum(axis=1))
        grid = c1_grid(steps.dt_s)
        self.z_lo, self.z_hi = float(grid.min()), float(grid.max())

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        b = b_of_z(np.clip(phi, self.z_lo, self.z_hi))
        return np.exp(-(self.rows0 * b[0] + self.rows @ b[1:]))


def _nelder_mead(
    cost: Callable[[np.ndarray], float], x0: np.ndarray, step: np.ndarray, xatol: float, fatol: float, maxiter: int
) -> optimize.OptimizeResult:
    """scipy's Nelder–Mead from x0 with the first simplex `step` wide along each axis."""
    simplex = np.vstack([x0, x0 + np.diag(step)])
    return optimize.minimize(
        cost,
        x0,
        method="Nelder-Mead",
        options={"initial_simplex": simplex, "xatol": xatol, "fatol": fatol, "maxiter": maxiter},
    )


@dataclass
class FormFit:
    """A fold's (or the whole log's) fit of a form whose C1 depends on the speed: its C1
    parameters φ, the least squares there, whether the search converged."""

    phi: np.ndarray
    fit: Fitted
    converged: bool


def fit_law(steps: Steps, roles: Roles, folds: bool = True, exact: bool = True) -> list[FormFit | str]:
    """The speed law per fold (or on the whole log): φ = (z0, γ) the best of the law's grid (every
    fold's Gram blocks at once, `Scan`), then Nelder–Mead from there (`exact`: to 1e-5 in φ and 1e-10
    of the train SSE; else a parabola's worth for scoring: 1e-2 in φ or 1e-5 of the SSE)."""
    law = LawC1(steps)
    grid = law.grid()
    scan = Scan(steps.only(roles.sensors), [law(phi) for phi in grid], folds)
    dz = float(law.z[1] - law.z[0]) if law.z.size > 1 else 0.1
    out: list[FormFit | str] = []
    for j, (k, fold) in enumerate(scan.folds):
        c2 = steps.W @ steps.c2_map(fold)
        why = fold.why or too_few(fold, roles, c2.shape[1] + 2, k)
        if why:
            out.append(why)
            continue
        _, cost, _ = scan.solve([roles], j)
        best = grid[int(np.argmin(cost[0]))]
        search = Search(steps, roles, fold, law, c2)
        tol, ftol = (1e-5, 1e-10) if exact else (1e-2, 1e-5)  # φ, and the train SSE relative
        res = _nelder_mead(search.cost, best, np.array([dz, 0.25]), tol, ftol * max(float(cost[0].min()), 1e-12), 400)
        phi = res.x if res.fun <= float(cost[0].min()) else best
        out.append(FormFit(np.asarray(phi, dtype=float), search.at(phi), bool(res.success)))
    return out


def fit_levels(steps: Steps, roles: Roles, z_constant: Sequence[float], folds: bool = True) -> list[FormFit | str]:
    """C1 per level per fold (or on the whole log), by Nelder–Mead from the fold's single C1
    (`z_constant`, one per fold) as compd.identify.ar1's fit searches it."""
    out: list[FormFit | str] = []
    for (k, fold), z in zip(steps.each(folds), z_constant, strict=True):
        c2 = steps.W @ steps.c2_map(fold)
        why = fold.why or too_few(fold, roles, c2.shape[1] + fold.nodes.size, k)
        if why or not math.isfinite(z):
            out.append(why or f"fold {k}: no single C1 to start from")
            continue
        search = Search(steps, roles, fold, LevelC1(steps, fold), c2)
        x0 = np.full(1 + fold.nodes.size, z)
        cost0 = search.cost(x0)
        res = optimize.minimize(
            search.cost,
            x0,
            method="Nelder-Mead",
            options={"xatol": 1e-5, "fatol": 1e-9 * max(cost0, 1e-12), "maxiter": 400 * x0.size},
        )
        out.append(FormFit(np.asarray(res.x, dtype=float), search.at(res.x), bool(res.success)))
    return out


def fold_scores(fits: Sequence[FormFit | str], steps: Steps, folds: bool = True) -> list[FoldScore]:
    """The held-out (SSE, rows) of each fold's fit, or why it could not be fitted."""
    return [
        f if isinstance(f, str) else (np.array([f.fit.held_sse]), np.array([fold.rows]))
        for f, (_, fold) in zip(fits, steps.each(folds), strict=True)
    ]

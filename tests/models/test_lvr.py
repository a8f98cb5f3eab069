"""LVR: the paper's PLS against scikit-learn, exact fast LOO Q², component selection, sample library."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.cross_decomposition import PLSRegression

from compd.errors import BadInput
from compd.identify.lvr import Q2_LIMIT, loo_press, rows_needed, sample_library, select_components
from compd.log import Log
from compd.models.lvr import LVR, fit_pls


def _data(n=40, p=6, q=2, seed=1):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, p)) * rng.uniform(0.5, 4, p) + 20.0
    Y = X @ rng.normal(size=(p, q)) + rng.normal(size=(n, q))
    return X, Y


def _sk(n_components):
    # tol/max_iter tight so sklearn's power iteration converges to the exact eigenvector
    return PLSRegression(n_components, tol=1e-30, max_iter=5000)


@pytest.mark.parametrize("q", [1, 2])
@pytest.mark.parametrize("h", [1, 3, 6])
def test_fit_pls_matches_sklearn(q, h):
    X, Y = _data(q=q)
    ours = fit_pls(X, Y, h)
    ref = _sk(h).fit(X, Y)
    assert ours.coef_.shape == (6, q)
    np.testing.assert_allclose(ours.coef_, ref.coef_.T, atol=1e-8)
    np.testing.assert_allclose(ours.predict(X), ref.predict(X).reshape(-1, q), atol=1e-8)


def test_fast_loo_equals_naive_refits():
    X, Y = _data(n=30, p=5)
    A = 4
    fast = loo_press(X, Y, A)
    ystd = Y.std(axis=0, ddof=1)
    naive = np.zeros(A)
    for h in range(1, A + 1):
        for i in range(len(X)):
            keep = np.arange(len(X)) != i
            m = _sk(h).fit(X[keep], Y[keep])
            naive[h - 1] += np.sum(((Y[i] - m.predict(X[i : i + 1])[0]) / ystd) ** 2)
    np.testing.assert_allclose(fast, naive, rtol=1e-7)


def test_fast_loo_chunks_agree():
    X, Y = _data(n=50, p=7)
    np.testing.assert_allclose(loo_press(X, Y, 5), loo_press(X, Y, 5, chunk_elems=7 * 7 * 3), rtol=1e-12)


def test_q2_selection_rule():
    X, Y = _data(n=60, p=8)
    h, q2, full = select_components(X, Y, 8)
    press = loo_press(X, Y, 8)
    expect = [1 - press[k] / full.ss_[k] for k in range(8)]
    np.testing.assert_allclose(q2, expect)
    first_bad = next((k for k, v in enumerate(q2) if v < Q2_LIMIT), len(q2))
    assert h == max(first_bad, 1)
    assert all(v >= Q2_LIMIT for v in q2[:h])


def _indexed(s):
    """A log whose row k reads (k, k²) and errors (3k): a library row's indices can be read back."""
    k = np.arange(float(s))
    return np.column_stack([k, k * k]), 3 * k[:, None]


def _indices(dX):
    """(i, j) of library rows W_i − W_j built from `_indexed` (i − j and i² − j² give both)."""
    diff = dX[:, 0]  # i − j
    total = dX[:, 1] / diff  # i + j
    return np.rint((total + diff) / 2).astype(int), np.rint((total - diff) / 2).astype(int)


def test_sample_library_keeps_eq11_rows():
    # eq. 11: from s = 12 rows with span P* = 4, rows i = 1 … s − P* (here 0 … 7), each
    # paired with row i + P_i, 1 ≤ P_i ≤ 4: the partner never falls past the last row
    X, Y = _indexed(12)
    for seed in range(20):
        dX, dY = sample_library(X, Y, 4, np.random.default_rng(seed))
        i, j = _indices(dX)
        assert dX.shape == (8, 2) and dY.shape == (8, 1)
        np.testing.assert_array_equal(i, np.arange(8))
        assert np.all((j - i >= 1) & (j - i <= 4)) and j.max() <= 11
        np.testing.assert_array_equal(dY[:, 0], 3 * (i - j))


def test_sample_library_steps_cover_the_span():
    X, Y = _indexed(403)
    dX, _ = sample_library(X, Y, 3, np.random.default_rng(5))
    i, j = _indices(dX)
    assert len(i) == 400
    counts = np.bincount(j - i, minlength=4)
    assert counts[0] == 0 and counts[1:].min() > 100  # 1, 2 and 3 drawn about 133 times each


def test_sample_library_span_limits():
    X, Y = _indexed(5)
    dX, _ = sample_library(X, Y, 4, np.random.default_rng(0))  # P* = s − 1: one row, 0 with 4
    np.testing.assert_array_equal(np.column_stack(_indices(dX)), [[0, 4]])
    for span in (0, 5, 9):
        with pytest.raises(ValueError, match="span"):
            sample_library(X, Y, span, np.random.default_rng(0))


def _log(n=200, seed=2):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 10.0
    T = 20 + np.outer(1 - np.exp(-t / 600), [3.0, 2.0, 1.0, 0.5]) + rng.normal(0, 0.05, (n, 4))
    E = (T - T[0]) @ np.array([[2.0, 0.5], [1.0, -1.0], [0.0, 0.3], [0.5, 0.0]])
    E += rng.normal(0, 0.1, E.shape)
    cols = ["t_s", "T1", "T2", "T3", "T4", "err_x1_um", "err_x2_um"]
    return Log("syn.csv", cols, np.column_stack([t, T, E]))


def test_lvr_fit_and_evaluate_agree():
    log = _log()
    res = LVR.fit(log, None, None)
    m = res.model
    assert m.outputs == ["x1", "x2"] and res.report["n_components"] >= 1
    assert len(res.report["q2"]) == 4 and set(res.report["influence"]) == {"T1", "T2", "T3", "T4"}
    X = log.matrix(m.inputs)
    P = type(m)(m.params, m.inputs, m.outputs).predict(X, log.t_s)
    m.start(X[0], 0.0)
    out = np.zeros(2)
    for i in (0, 50, 199):
        m.evaluate(X[i], 0.0, out)
        np.testing.assert_allclose(out, P[i], atol=1e-12)
    E = log.matrix(["err_x1_um", "err_x2_um"])
    assert np.sqrt(np.mean((P - E) ** 2)) < 0.3


def test_lvr_library_fit_keeps_s_minus_span_rows():
    res = LVR.fit(_log(), None, None, library_span=20, seed=1)
    assert res.report["fit_rows"] == 200 - 20 and res.report["library_span"] == 20
    assert res.report["n_components"] >= 1


def test_lvr_library_span_leaving_too_few_rows_is_refused():
    log = _log()  # 200 rows, 4 inputs: Q² selection tries 4 components, which need 7 rows
    assert rows_needed(4) == 7
    res = LVR.fit(log, None, None, library_span=193)  # keeps 7 rows: enough
    assert res.report["fit_rows"] == 7
    with pytest.raises(BadInput, match=r"--option library_span: span 194 keeps 6 .* at least 7"):
        LVR.fit(log, None, None, library_span=194)
    with pytest.raises(BadInput, match="library_span: span 250 keeps 0"):
        LVR.fit(log, None, None, library_span=250)
    # the rule counts the components asked for: 2 of them need only 5 rows
    assert LVR.fit(log, None, None, library_span=195, n_components=2).report["fit_rows"] == 5
    with pytest.raises(BadInput, match="library_span"):
        LVR.fit(log, None, None, library_span=196, n_components=2)
    short = Log("s.csv", log.columns, log.data[:7])  # a library keeps at most s − 1 rows
    with pytest.raises(BadInput, match="s.csv: 7 rows are too few: a sample library"):
        LVR.fit(short, None, None, library_span=1)


def test_lvr_bad_inputs():
    log = _log()
    const = Log("c.csv", log.columns, log.data.copy())
    const.data[:, 2] = 21.0
    with pytest.raises(BadInput, match="T2.*constant|constant"):
        LVR.fit(const, None, None)
    with pytest.raises(BadInput, match="too few"):
        LVR.fit(Log("s.csv", log.columns, log.data[:5]), None, None, n_components=4)
    with pytest.raises(BadInput, match="unknown fit option"):
        LVR.fit(log, None, None, components=3)

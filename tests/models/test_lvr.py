"""LVR: the paper's PLS against scikit-learn, exact fast LOO Q², blocked cross-validation.

Also component selection and the sample library.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter
from sklearn.cross_decomposition import PLSRegression

from compd.core.errors import BadInput
from compd.identify import FITS
from compd.identify.lvr import (
    Q2_LIMIT,
    blocked_press,
    blocked_q2,
    coef_path,
    equal_blocks,
    fewest_within,
    guard_rows_from_residuals,
    held_out_blocks,
    loo_press,
    rows_needed,
    sample_library,
    select_components,
    stretches,
)
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
    res = FITS.get(LVR.kind)(log, None, None)
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
    res = FITS.get(LVR.kind)(_log(), None, None, library_span=20, seed=1)
    assert res.report["fit_rows"] == 200 - 20 and res.report["library_span"] == 20
    assert res.report["n_components"] >= 1


def test_lvr_library_span_leaving_too_few_rows_is_refused():
    log = _log()  # 200 rows, 4 inputs: Q² selection tries 4 components, which need 7 rows
    loo = {"selection": "loo"}  # the paper's limits: what its leave-one-out needs
    assert rows_needed(4) == 7
    res = FITS.get(LVR.kind)(log, None, None, library_span=193, **loo)  # keeps 7 rows: enough
    assert res.report["fit_rows"] == 7
    with pytest.raises(BadInput, match=r"--option library_span: span 194 keeps 6 .* at least 7"):
        FITS.get(LVR.kind)(log, None, None, library_span=194, **loo)
    with pytest.raises(BadInput, match="library_span: span 250 keeps 0"):
        FITS.get(LVR.kind)(log, None, None, library_span=250, **loo)
    # the rule counts the components asked for: 2 of them need only 5 rows
    assert FITS.get(LVR.kind)(log, None, None, library_span=195, n_components=2, **loo).report["fit_rows"] == 5
    with pytest.raises(BadInput, match="library_span"):
        FITS.get(LVR.kind)(log, None, None, library_span=196, n_components=2, **loo)
    short = Log("s.csv", log.columns, log.data[:7])  # a library keeps at most s − 1 rows
    with pytest.raises(BadInput, match="s.csv: 7 rows are too few: a sample library"):
        FITS.get(LVR.kind)(short, None, None, library_span=1, **loo)


def test_lvr_library_span_limit_of_blocked_selection():
    # blocked over 5 stretches: holding out the longest still leaves 4 + 3 rows to fit,
    # so 9 rows (blocks of 2, 2, 1, 2, 2); the message names the blocks
    log = _log()
    assert rows_needed(4, 5) == 9 and rows_needed(4, 2) == 14
    assert FITS.get(LVR.kind)(log, None, None, library_span=191).report["fit_rows"] == 9
    with pytest.raises(
        BadInput, match=r"span 192 keeps 8 .* 4 components and 5 cross-validation blocks needs at least 9"
    ):
        FITS.get(LVR.kind)(log, None, None, library_span=192)


def test_lvr_bad_inputs():
    log = _log()
    const = Log("c.csv", log.columns, log.data.copy())
    const.data[:, 2] = 21.0
    with pytest.raises(BadInput, match="T2.*constant|constant"):
        FITS.get(LVR.kind)(const, None, None)
    with pytest.raises(BadInput, match="too few"):
        FITS.get(LVR.kind)(Log("s.csv", log.columns, log.data[:5]), None, None, n_components=4)
    with pytest.raises(BadInput, match="unknown fit option"):
        FITS.get(LVR.kind)(log, None, None, components=3)


# --- selection: blocked cross-validation (compd's default) against the paper's LOO ---------------


def _ar1(n, k, rho, rng):
    """k AR(1) series of unit variance, n rows: x_i = ρ x_(i−1) + √(1 − ρ²) e_i."""
    e = rng.normal(size=(n, k)) * np.sqrt(1 - rho**2)
    e[0] = rng.normal(size=k)
    return lfilter([1.0], [1.0, -rho], e, axis=0)


def _one_latent_log(seed, n=15000, p=19, rho=0.99):
    """1 Hz log: one latent thermal state s (heats and cools every 3000 s, τ = 1500 s) drives
    19 sensors and the error; sensors and error carry AR(1) noise with ρ = 0.99 per row."""
    rng = np.random.default_rng(seed)
    target = np.where((np.arange(n) // 3000) % 2 == 0, 5.0, 1.0)
    a = 1 / 1500
    s = lfilter([a], [1.0, -(1 - a)], target)
    T = 20 + np.outer(s, rng.uniform(0.5, 2.0, p)) + 0.5 * _ar1(n, p, rho, rng)
    E = 3.0 * s[:, None] + 3.0 * _ar1(n, 1, rho, rng)
    cols = ["t_s", *(f"T{j}" for j in range(p)), "err_x_um"]
    return Log("ar1.csv", cols, np.column_stack([np.arange(n, dtype=float), T, E]))


def test_blocked_selects_the_one_latent_component_loo_overselects():
    fit_rows = 6000  # the first 100 min; the rest is a later stretch the fits never see
    rms = {"loo": [], "blocked": []}
    for seed in range(6):
        log = _one_latent_log(seed)
        train = Log(log.file, log.columns, log.data[:fit_rows])
        fits = {sel: FITS.get(LVR.kind)(train, None, None, selection=sel, max_components=6) for sel in rms}
        loo, blocked = fits["loo"].report, fits["blocked"].report
        assert blocked["selection"] == "blocked" and loo["selection"] == "loo"
        # LOO: each left-out row's neighbours, with nearly its noise, stay in the fit
        assert loo["n_components"] > 1, seed
        assert blocked["n_components"] == 1, seed
        cv = blocked["cv"]
        assert cv["split"] == "equal" and len(cv["blocks"]) == 5 and cv["guard"] == "autocorrelation"
        assert 50 <= cv["guard_rows"] <= 600  # ρ = 0.99: ≈ 300 rows, estimated from 6000
        # the second component fits noise: it cuts the held-out error by less than 5 % RMS
        assert blocked["q2"][1] < Q2_LIMIT <= blocked["q2"][0]
        # the later stretch: rises from the log's first reading, as in the fit
        for sel, res in fits.items():
            m = res.model
            pred = type(m)(m.params, m.inputs, m.outputs).predict(log.data[:, 1:-1], log.t_s)[fit_rows:]
            rms[sel].append(float(np.sqrt(np.mean((log.data[fit_rows:, -1:] - pred) ** 2))))
    # the one component predicts the stretch neither fit saw better (by chance not on every day)
    assert sum(rms["blocked"]) < 0.97 * sum(rms["loo"]), rms
    assert sum(b < o for b, o in zip(rms["blocked"], rms["loo"], strict=True)) >= 5, rms


def test_coef_path_is_each_shorter_fit():
    X, Y = _data(n=50, p=6)
    coefs, intercepts = coef_path(fit_pls(X, Y, 5))
    for k in range(1, 6):
        ref = fit_pls(X, Y, k)
        np.testing.assert_allclose(coefs[k - 1], ref.coef_, atol=1e-10)
        np.testing.assert_allclose(intercepts[k - 1], ref.intercept_, atol=1e-10)


def test_blocked_press_equals_refits_without_the_block_and_its_guard():
    X, Y = _data(n=60, p=5)
    blocks, guard, A = equal_blocks(60, 4), 3, 3
    press = blocked_press(X, Y, A, blocks, guard)
    ystd = Y.std(axis=0, ddof=1)
    rows = np.arange(60)
    for k, (lo, hi) in enumerate(blocks):
        train = (rows < lo - guard) | (rows >= hi + guard)
        assert train.sum() == 60 - 15 - (0 if k == 0 else 3) - (0 if k == 3 else 3)
        np.testing.assert_allclose(press[k, 0], np.sum(((Y[lo:hi] - Y[train].mean(axis=0)) / ystd) ** 2))
        for h in range(1, A + 1):
            m = _sk(h).fit(X[train], Y[train])
            np.testing.assert_allclose(press[k, h], np.sum(((Y[lo:hi] - m.predict(X[lo:hi])) / ystd) ** 2), rtol=1e-8)
    q2 = blocked_q2(press)
    total = press.sum(axis=0)
    np.testing.assert_allclose(q2, 1 - total[1:] / total[:-1])


def test_fewest_components_within_five_percent_rms_of_the_best():
    # the 6 h lathe log's held-out PRESS: the 4th component adds nothing, the 5th halves it;
    # stopping at the first useless component (the paper's sequential rule) would keep 3
    lathe = [629.2, 258.0, 144.7, 150.2, 70.7, 64.8, 58.5]
    assert fewest_within(lathe, Q2_LIMIT) == 6  # 64.8 · 0.9025 = 58.48 ≤ 58.5: just within
    assert fewest_within(lathe, 0.2) == 5
    # the gantry's training day: 2 is within 5 % RMS of the best (3), more only fit noise
    gantry = [392.9, 143.0, 132.2, 133.9, 180.0, 155.4]
    assert fewest_within(gantry, Q2_LIMIT) == 2
    assert fewest_within(gantry, 0.0) == 3  # no tolerance: the minimum
    assert fewest_within(gantry, -0.1) == 3  # a negative limit: still the minimum
    assert fewest_within(gantry, 1.0) == 1


def test_guard_band_from_autocorrelation():
    rng = np.random.default_rng(4)
    # AR(1), ρ = 0.99: autocorrelation ρ^L < 0.05 from L = 299 on
    assert 220 <= guard_rows_from_residuals(_ar1(200_000, 2, 0.99, rng), 5000) <= 380
    assert guard_rows_from_residuals(rng.normal(size=(5000, 2)), 1000) == 1  # white: lag 1 already
    assert guard_rows_from_residuals(np.cumsum(rng.normal(size=5000)), 100) == 100  # never: the limit
    assert guard_rows_from_residuals(np.ones(50), 10) == 0  # no variance, no noise to share


def test_blocks_are_the_days_of_a_log_with_gaps():
    day = np.arange(0.0, 36000.0, 60.0)  # 10 h at 60 s, then 14 h off
    t = np.concatenate([day, day + 86400, day + 2 * 86400])
    blocks, split = held_out_blocks(t, 5, 7)
    assert split == "gaps" and blocks == [(0, 600), (600, 1200), (1200, 1800)]
    assert stretches(t[:600]) == [(0, 600)]  # a log without gaps: one stretch, cut into equal blocks
    assert held_out_blocks(t[:600], 5, 7) == (equal_blocks(600, 5), "equal")
    # a stretch shorter than half a block (a restart) joins its neighbour
    short = np.concatenate([t, [4 * 86400.0, 4 * 86400.0 + 60]])
    assert held_out_blocks(short, 5, 7)[0] == [(0, 600), (600, 1200), (1200, 1802)]
    # a pause of 30 min in a 60 s log is not a gap (under GAP_S); one of 2 h is
    assert len(stretches(np.concatenate([day, day[-1] + 1800 + day]))) == 1
    assert len(stretches(np.concatenate([day, day[-1] + 7200 + day]))) == 2
    assert equal_blocks(9, 5) == [(0, 2), (2, 4), (4, 5), (5, 7), (7, 9)]


def test_lvr_fit_by_day_reports_the_days_as_blocks():
    log = _log()  # 200 rows at 10 s: three "days" of 200 rows, 12 h apart
    days = [log.data.copy() for _ in range(3)]
    for d, data in enumerate(days):
        data[:, 0] += d * 43200.0
    res = FITS.get(LVR.kind)(Log("days.csv", log.columns, np.vstack(days)), None, None)
    cv = res.report["cv"]
    assert cv["split"] == "gaps" and cv["blocks"] == [[0, 199], [200, 399], [400, 599]]
    assert cv["guard_rows"] == 0 and cv["guard"] == "none"
    assert len(res.report["press"]) == len(res.report["q2"]) == 4


def test_selection_loo_is_the_papers():
    log = _log()
    res = FITS.get(LVR.kind)(log, None, None, selection="loo")
    R = log.matrix(["T1", "T2", "T3", "T4"])
    R = R - R[0]
    Y = log.matrix(["err_x1_um", "err_x2_um"])
    h, q2, full = select_components(R, Y, 4)
    assert res.report["selection"] == "loo" and "cv" not in res.report
    assert res.report["n_components"] == h
    np.testing.assert_allclose(res.report["q2"], q2, rtol=1e-12)
    np.testing.assert_allclose(res.report["press"], loo_press(R, Y, 4), rtol=1e-9)
    np.testing.assert_allclose(res.model.params.coef_um_per_k, fit_pls(R, Y, h).coef_, atol=1e-12)


def test_forced_components_report_the_blocked_cross_validation():
    res = FITS.get(LVR.kind)(_log(), None, None, n_components=3)
    assert res.report["n_components"] == 3 and res.model.params.n_components == 3
    assert res.report["selection"] == "blocked" and len(res.report["q2"]) == 3


@pytest.mark.parametrize(
    ("option", "match"),
    [
        ({"selection": "kfold"}, r"--option selection: Input should be 'blocked' or 'loo' \(got 'kfold'\)"),
        ({"cv_blocks": 1}, "--option cv_blocks: Input should be greater than or equal to 2"),
        ({"cv_blocks": 51}, "--option cv_blocks: Input should be less than or equal to 50"),
        ({"cv_blocks": "many"}, "--option cv_blocks: Input should be a valid integer"),
        ({"cv_guard_rows": -1}, "--option cv_guard_rows: Input should be greater than or equal to 0"),
        # 200 rows in blocks of 40: holding out rows 80..119 with 80 rows each side leaves none
        (
            {"cv_guard_rows": 80},
            r"--option cv_guard_rows: a guard band of 80 rows leaves 0 rows to fit 4 components"
            r", which need 7; at most 76 here",
        ),
        (
            {"cv_blocks": 50, "library_span": 151},
            "span 151 keeps 49 .* and 50 cross-validation blocks needs at least 50",
        ),
    ],
)
def test_bad_selection_options(option, match):
    with pytest.raises(BadInput, match=match) as e:
        FITS.get(LVR.kind)(_log(), None, None, **option)
    assert "\n" not in str(e.value)

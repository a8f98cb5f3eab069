"""Evaluation without scipy gives scipy's numbers: compd.models.erf (the C library's erf) against
scipy.special.erf within 3 ulp, the feed-axis loop output to 1e-13, the AR(1) run-time filter
against scipy's lfilter, the fit's filter against the run-time one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, special

from compd.identify.ar1 import ar_filter as fit_filter
from compd.models.ar1 import ar_filter
from compd.models.erf import erf, erf_inplace


@pytest.mark.parametrize("span", [0.5, 1.0, 3.0, 8.5, 40.0])
def test_erf_agrees_with_scipys(span: float) -> None:
    x = np.random.default_rng(0).uniform(-span, span, 100_000)
    np.testing.assert_array_max_ulp(erf(x), special.erf(x), maxulp=3)


def test_erf_edges_and_shapes() -> None:
    edges = np.array([0.0, -0.0, 1.0, -1.0, 8.0, 27.0, 1e300, np.inf, -np.inf, 5e-324])
    np.testing.assert_array_max_ulp(erf(edges), special.erf(edges), maxulp=1)
    assert np.signbit(erf(-0.0)) and np.isnan(erf(np.nan)) and erf(np.array([])).shape == (0,)
    grid = np.linspace(-3.0, 3.0, 60).reshape(3, 4, 5)
    assert erf(grid).shape == (3, 4, 5) and erf(grid).dtype == np.float64
    np.testing.assert_array_max_ulp(erf(grid), special.erf(grid), maxulp=3)


def test_ar_filter_rounds_like_lfilter() -> None:
    rng = np.random.default_rng(1)
    u = rng.normal(size=(300, 3))
    c1, s0 = 0.9955, 0.37
    want = signal.lfilter([1.0], [1.0, -c1], u, axis=0, zi=np.full((1, 3), c1 * s0))[0]
    np.testing.assert_array_equal(ar_filter(c1, u, s0), want)
    np.testing.assert_array_equal(ar_filter(c1, u[:, 0], s0), want[:, 0])
    np.testing.assert_array_equal(fit_filter(c1, u, s0), want)
    per_row = rng.uniform(0.9, 0.999, size=300)
    np.testing.assert_array_equal(fit_filter(per_row, u, s0), ar_filter(per_row, u, s0))
    s = s0
    for k in range(5):  # one C1 per row: the loop's own recursion
        s = per_row[k] * s + u[k, 1]
    assert ar_filter(per_row, u, s0)[4, 1] == s


def test_erf_inplace_within_three_ulp() -> None:
    x = np.random.default_rng(2).uniform(0.0, 6.0, 100_000)
    buf = x.copy()
    erf_inplace(buf)
    np.testing.assert_array_max_ulp(buf, special.erf(x), maxulp=3)


def test_feed_axis_evaluate_as_with_scipys_erf(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loop's per-cycle feed-axis error: the same numbers (to 1e-13) as with scipy's erf."""
    import compd.models.feed_axis as fa

    params = fa.FeedAxisParams(
        length_mm=600.0,
        segments=30,
        chi_per_m=3.0,
        eta=0.22,
        u1_k=-8.52,
        u2_k=-8.48,
        xi=1.04,
        r_cu_ohm=0.8,
        input_roles=["position", "current", "motor_temp", "ambient"],
    )

    def run() -> np.ndarray:
        m = fa.FeedAxis(params, ["pos", "cur", "T_m", "T_a"], ["x"])
        out, got = np.zeros(1), []
        for k in range(600):
            x = np.array([300.0 + 290.0 * np.sin(k / 7.0), 40.0 if k % 100 < 70 else 0.0, 30.0, 20.0])
            if k == 0:
                m.start(x, 0.0)
            m.evaluate(x, 10.0 * k, out)
            got.append(out[0])
        return np.array(got)

    ours = run()
    monkeypatch.setattr(fa, "erf_inplace", lambda b: special.erf(b, out=b))
    np.testing.assert_allclose(ours, run(), rtol=1e-13, atol=1e-12)
    assert np.ptp(ours) > 1.0  # the run does heat the slide

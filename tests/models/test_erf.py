"""Evaluation without scipy gives scipy's numbers: compd.models.erf against scipy.special.erf, the
AR(1) run-time filter against scipy's lfilter, the fit's filter against the run-time one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, special

from compd.identify.ar1 import ar_filter as fit_filter
from compd.models.ar1 import ar_filter
from compd.models.erf import erf


@pytest.mark.parametrize("span", [0.5, 1.0, 3.0, 8.5, 40.0])
def test_erf_is_scipys(span: float) -> None:
    x = np.random.default_rng(0).uniform(-span, span, 200_000)
    # the same polynomials in the same order: equal here; one ulp allowed for another CPU's exp
    np.testing.assert_array_max_ulp(erf(x), special.erf(x), maxulp=1)
    assert np.mean(erf(x) == special.erf(x)) > 0.999


def test_erf_edges_shapes_and_out() -> None:
    edges = np.array([0.0, -0.0, 1.0, -1.0, np.nextafter(1.0, 2.0), np.nextafter(8.0, 0.0), 8.0, 27.0,
                      1e300, np.inf, -np.inf, 5e-324, 1e-310])
    np.testing.assert_array_equal(erf(edges), special.erf(edges))
    assert np.signbit(erf(-0.0)) and np.isnan(erf(np.nan)) and erf(np.array([])).shape == (0,)
    assert erf(0.3) == special.erf(0.3)
    grid = np.linspace(-3.0, 3.0, 60).reshape(3, 4, 5)
    np.testing.assert_array_max_ulp(erf(grid), special.erf(grid), maxulp=1)
    buf = np.linspace(0.0, 3.0, 30)
    want = special.erf(buf)
    assert erf(buf, out=buf) is buf
    np.testing.assert_array_max_ulp(buf, want, maxulp=1)


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

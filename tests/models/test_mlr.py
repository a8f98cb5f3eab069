"""MLR baseline: recovers linear coefficients on temperature rises; evaluate equals predict."""

from __future__ import annotations

import numpy as np

from compd.identify import FITS
from compd.log import Log
from compd.models.mlr import MLR


def test_mlr_recovers_coefficients():
    rng = np.random.default_rng(0)
    n = 100
    T = 20 + rng.normal(0, 1, (n, 3)).cumsum(axis=0) * 0.1
    B = np.array([[1.5], [-0.7], [3.0]])
    E = 0.4 + (T - T[0]) @ B
    log = Log("m.csv", ["t_s", "A", "B", "C", "err_z_um"], np.column_stack([np.arange(n), T, E]))
    m = FITS.get(MLR.kind)(log, None, None).model
    np.testing.assert_allclose(m.params.coef_um_per_k, B, atol=1e-9)
    np.testing.assert_allclose(m.params.intercept_um, [0.4], atol=1e-9)
    P = MLR(m.params, m.inputs, m.outputs).predict(T, np.arange(n))
    m.start(T[0], 0.0)
    out = np.zeros(1)
    m.evaluate(T[7], 0.0, out)
    assert abs(out[0] - P[7, 0]) < 1e-12
    state = m.get_state()
    m2 = MLR(m.params, m.inputs, m.outputs)
    m2.set_state(state, 100.0)
    m2.evaluate(T[7], 0.0, out)
    assert abs(out[0] - P[7, 0]) < 1e-12

"""PT100 realism: class-A tolerance, quantization, noise, drift, batch reads."""

from __future__ import annotations

import numpy as np

from hil_sim.pt100 import Pt100Bank


def test_readings_stay_within_class_a_plus_quantization():
    rng = np.random.default_rng(0)
    bank = Pt100Bank(200, rng, noise_c=0.0)
    for t in (0.0, 25.0, 80.0):
        v = bank.read(np.full(200, t), 0.0)
        tol = 0.15 + 0.002 * abs(t)
        assert np.all(np.abs(v - t) <= tol + 0.05 + 1e-9)
        assert np.allclose(v * 10, np.round(v * 10))  # 0.1 °C steps
        assert np.std(v - t) > 0.03  # offsets differ between sensors


def test_noise_and_drift():
    rng = np.random.default_rng(1)
    drift = np.zeros(3)
    drift[2] = 0.1
    bank = Pt100Bank(3, rng, noise_c=0.05, tolerance=False, resolution_c=0.0, drift_c_per_h=drift)
    true = np.full((5000, 3), 20.0)
    t = np.full((5000, 1), 36000.0)  # 10 h
    v = bank.read(true, t)
    assert v.shape == (5000, 3)
    np.testing.assert_allclose(v.std(axis=0), 0.05, rtol=0.1)
    np.testing.assert_allclose(v.mean(axis=0), [20.0, 20.0, 21.0], atol=0.01)


def test_a_channel_without_a_reading_is_an_open_wire() -> None:
    """A plant's unplugged sensor (NaN) reads as burnout on every module kind, never as a number."""
    from hil_sim.devices.pt100 import Pt100Transmitter

    tx = Pt100Transmitter(["T_col_top", "T_xi"], [float("nan"), 21.5])
    (state, _), ok = tx.readings()
    assert state == "burnout" and ok == ("ok", 21.5)

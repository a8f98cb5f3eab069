"""Per-evaluation cost of every model kind, as the loop calls it (the bench JSON's `model_eval_us`).

`BUILDERS` makes a model of each kind with the params `compd fit` writes; `compd bench`
(rig.bench) and tests/bench time them with `model_eval_us`, and the test that the daemon
stays light (tests/models/test_runtime_imports.py) steps one of each.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from compd.models.base import Model


def _lvr(kind: str) -> Model:
    from compd.models.lvr import LVR, LVRParams
    from compd.models.mlr import MLR, RiseLinearParams

    rng = np.random.default_rng(0)
    p, q = 19, 2  # paper 002: 19 sensors, two axes
    coef = rng.normal(size=(p, q)).tolist()
    inputs = [f"T{i}" for i in range(p)]
    if kind == "lvr":
        return LVR(LVRParams(coef_um_per_k=coef, intercept_um=[0.0, 0.0], n_components=4), inputs, ["x1", "x2"])
    return MLR(RiseLinearParams(coef_um_per_k=coef, intercept_um=[0.0, 0.0]), inputs, ["x1", "x2"])


def _xi() -> Model:
    from compd.models.xi_spindle import LiftParams, RadialParams, XiSpindle, XiSpindleParams

    params = XiSpindleParams(  # the form `compd fit` writes: the axial lift, fitted ring gains
        alpha_per_k=13.6e-6,
        length_mm=165.0,
        lift=LiftParams(k_um_per_rpm2=1e-7),
        radial=RadialParams(outer_gain=0.72, inner_gain=0.61),
    )
    return XiSpindle(params, ["T_xi", "T_in", "T_out", "speed_rpm"], ["z", "x"])


def _ar1() -> Model:
    from compd.models.ar1 import AR1, AR1Params

    params = AR1Params(
        dt_s=60.0,
        c1=0.9955,
        c2_table=[(1000.0, 0.089), (1500.0, 0.121), (2000.0, 0.22)],
        c3_um_per_k=0.05,
        bed_gain_um_per_k=[12.0],
        spindle_sign=-1,
    )
    return AR1(params, ["speed_rpm", "T3", "T_amb"], ["z"])


def _feed_axis() -> Model:
    from compd.models.feed_axis import FeedAxis, FeedAxisParams

    params = FeedAxisParams(
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
    return FeedAxis(params, ["pos_x_mm", "current_x_a", "T_motor", "T_amb"], ["x"])


BUILDERS: dict[str, Callable[[], Model]] = {
    "feed_axis": _feed_axis,
    "lvr": lambda: _lvr("lvr"),
    "xi_spindle": _xi,
    "ar1": _ar1,
    "mlr": lambda: _lvr("mlr"),
}

_INPUTS: dict[str, Callable[[int], np.ndarray]] = {
    "feed_axis": lambda n: np.array([300.0, 40.0, 30.0, 20.0]),
    "xi_spindle": lambda n: np.array([25.0, 24.0, 23.0, 6000.0]),
    "ar1": lambda n: np.array([1500.0, 21.0, 20.5]),
}


def model_eval_us(evaluations: int = 5000) -> dict[str, float]:
    """{kind: median µs per `evaluate`} for every kind, each timed call by call."""
    out: dict[str, float] = {}
    perf = time.perf_counter_ns
    for kind, build in BUILDERS.items():
        model = build()
        n_in = len(model.inputs)
        x = _INPUTS.get(kind, lambda n: np.full(n, 20.0))(n_in).astype(float)
        model.start(x - 1.0 if kind in ("lvr", "mlr") else x, 0.0)
        y = np.zeros(len(model.outputs))
        times = np.empty(evaluations)
        t_s = 1.0
        for i in range(evaluations):
            t_s += 0.002
            a = perf()
            model.evaluate(x, t_s, y)
            times[i] = perf() - a
        out[kind] = float(np.median(times) / 1000.0)
    return out

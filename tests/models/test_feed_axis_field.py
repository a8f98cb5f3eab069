"""Feed axis, compd's field form: gains recovered, evaluate = predict, the Siemens line.

Also: slide sensors found, the form picked held out.
"""

from __future__ import annotations

import numpy as np
import pytest

from compd.core.errors import BadInput
from compd.identify import feed_axis as fit_fa
from compd.log import Log
from compd.models.feed_axis import (
    FeedAxis,
    FeedAxisParams,
    SlideField,
    copper_loss_w,
    error_um,
    heat_j,
)

ALPHA = 11.5e-6
L_MM = 600.0
SENSORS_MM = (0.0, 150.0, 300.0, 450.0, 600.0)
G_I, G_R, G_A, B_TABLE = 1.3, -1.1, 0.4, 0.9
G_C = 0.25  # the base before the stroke's start: the same growth at every position


def _truth_integral_um(rises: np.ndarray, y_mm: float) -> tuple[float, float]:
    """α ∫_0^y and α ∫_0^L of the field interpolated linearly between the sensors, on a fine grid."""
    grid = np.linspace(0.0, L_MM, 6001)
    field = np.interp(grid, SENSORS_MM, rises)
    upto = grid <= y_mm
    g, f = grid[upto], field[upto]
    part = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(g))) + float(np.interp(y_mm, grid, field) + f[-1]) * 0.5 * (
        y_mm - g[-1]
    )
    whole = float(np.sum(0.5 * (field[1:] + field[:-1]) * np.diff(grid)))
    return ALPHA * 1e3 * part, ALPHA * 1e3 * whole


def _field_log(hours: float = 8.0, seed: int = 0, noise_um: float = 0.0) -> Log:
    """A slide heated where the coil works (one end, then the other) in a drifting room."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600.0, 30.0)
    rows = []
    for k, ts in enumerate(t):
        h = ts / 3600.0
        amb = 20.0 + 0.3 * np.sin(h / 2.0)
        centre = 150.0 if (h % 4.0) < 2.0 else 450.0
        heat = 3.0 * (1.0 - np.exp(-h / 1.5))
        base = np.array([amb - 20.0 + heat * np.exp(-(((s - centre) / 200.0) ** 2)) for s in SENSORS_MM])
        table = 1.5 * heat / 3.0 + 0.2 * np.sin(h)
        y = (k * 37.0) % L_MM
        part, whole = _truth_integral_um(base, y)
        e = G_I * part + G_R * whole * y / L_MM + G_C * whole + G_A * ALPHA * 1e3 * y * (amb - 20.0) + B_TABLE * table
        rows.append([ts, *(20.0 + base), amb, 20.0 + table, y, e + rng.normal(0.0, noise_um)])
    cols = ["t_s", *[f"T_base_{int(s):03d}" for s in SENSORS_MM], "T_amb", "T_table", "pos_y_mm", "err_y_um"]
    return Log("field.csv", cols, np.asarray(rows))


def test_field_fit_recovers_gains_and_finds_the_sensors_by_name():
    log = _field_log()
    res = fit_fa.fit(log, None, None, form="field", length_mm=L_MM)
    f = res.model.params.field
    assert res.report["slide_sensors"] == {f"T_base_{int(s):03d}": s for s in SENSORS_MM}
    assert res.report["ambient"] == "T_amb" and res.report["offsets"] == ["T_table"]
    assert f.gain_integral == pytest.approx(G_I, rel=1e-3)
    assert f.gain_restraint == pytest.approx(G_R, rel=1e-3)
    assert f.gain_constant == pytest.approx(G_C, rel=1e-3)
    assert f.gain_ambient == pytest.approx(G_A, rel=1e-3)
    assert f.offset_um_per_k == pytest.approx([B_TABLE], rel=1e-3)


def test_evaluate_equals_predict_and_the_siemens_line_is_the_least_squares_line():
    log = _field_log(hours=3.0)
    model = fit_fa.fit(log, None, None, form="field", length_mm=L_MM).model
    X, t = log.matrix(model.inputs), log.t_s
    pred = FeedAxis(model.params, model.inputs, model.outputs).predict(X, t)[:, 0]
    live = FeedAxis(model.params, model.inputs, model.outputs)
    live.start(X[0], t[0])
    out = np.zeros(1)
    got = []
    for i in range(len(t)):
        live.evaluate(X[i], t[i], out)
        got.append(out[0])
    assert np.max(np.abs(np.asarray(got) - pred)) < 1e-9
    # the same params reduced to K0 + tanβ (P − P0): the line fitted to E over the stroke
    lin = FeedAxis(model.params.model_copy(update={"linear_p0_mm": 250.0}), model.inputs, model.outputs)
    lin.start(X[0], t[0])
    i = len(t) - 1
    lin.evaluate(X[i], t[i], out)
    slope, p0 = lin.linear_terms()[0]
    ys = np.linspace(0.0, L_MM, model.params.segments + 1)
    Xs = np.repeat(X[i : i + 1], ys.size, axis=0)
    Xs[:, model.inputs.index("pos_y_mm")] = ys
    ref = FeedAxis(model.params, model.inputs, model.outputs)
    ref.start(X[0], t[0])
    e_line = np.array([ref._field.predict(Xs[j : j + 1])[0] for j in range(ys.size)])
    k0_ref, slope_ref = np.polynomial.polynomial.polyfit(ys - 250.0, e_line, 1)
    assert p0 == 250.0
    assert out[0] == pytest.approx(k0_ref, abs=1e-9) and slope == pytest.approx(slope_ref, abs=1e-12)


def test_state_keeps_the_reference_readings():
    log = _field_log(hours=2.0)
    model = fit_fa.fit(log, None, None, form="field", length_mm=L_MM).model
    X, t = log.matrix(model.inputs), log.t_s
    a = FeedAxis(model.params, model.inputs, model.outputs)
    a.start(X[0], t[0])
    out_a, out_b = np.zeros(1), np.zeros(1)
    a.evaluate(X[100], t[100], out_a)
    b = FeedAxis(model.params, model.inputs, model.outputs)
    b.set_state(a.get_state(), elapsed_s=60.0)
    b.start(X[100], t[100])  # a restart mid-run: the references stay those of the run's start
    b.evaluate(X[100], t[100], out_b)
    assert out_b[0] == pytest.approx(out_a[0]) and abs(out_a[0]) > 0.5


def test_auto_picks_the_field_form_where_it_predicts_better_and_says_so():
    log = _field_log(noise_um=0.05)
    cols = log.columns + ["current_y_a"]
    log = Log(log.file, cols, np.column_stack([log.data, np.full(len(log), 20.0)]))
    res = fit_fa.fit(log, None, None, length_mm=L_MM, r_cu_ohm=1.0)
    sel = res.report["form_selection"]
    assert res.report["form"] == "field"
    assert sel["held_out_rmse_um"]["field"] < sel["held_out_rmse_um"]["analytic"]
    assert res.model.params.field is not None


def test_auto_keeps_the_analytic_form_on_a_log_without_slide_sensors():
    rows, t = [], 0.0
    for _ in range(3):
        for y in np.arange(0.0, 601.0, 20.0):
            rows.append([t, y, 30.0])
            t += 10.0
    rows = np.asarray(rows)
    true = FeedAxisParams(
        length_mm=600, chi_per_m=8.0, eta=0.2, u1_k=2.0, u2_k=-0.3, r_cu_ohm=0.8, input_roles=["position", "current"]
    )
    e = error_um(rows[:, 0], heat_j(rows[:, 0], copper_loss_w(rows[:, 2], 0.8, 0.0)), rows[:, 1], true)
    log = Log("a.csv", ["t_s", "pos_x_mm", "current_x_a", "err_x_um"], np.column_stack([rows, e]))
    res = fit_fa.fit(log, None, None, r_cu_ohm=0.8, length_mm=600)
    assert res.report["form"] == "analytic" and res.model.params.field is None
    assert res.report["form_selection"]["method"] == "the only form the log carries"


def test_eta_is_the_dimensionless_share_with_the_slide_volume():
    volume_m3 = 0.6 * 0.012  # a 600 mm slide of 120 cm²
    true = FeedAxisParams(
        length_mm=600,
        chi_per_m=8.0,
        eta=0.25,
        u1_k=2.0,
        u2_k=-0.3,
        r_cu_ohm=0.8,
        input_roles=["position", "current"],
        slide_volume_m3=volume_m3,
    )
    rows, t = [], 0.0
    for _ in range(4):
        for _ in range(60):
            rows.append([t, 300.0, 15.0])
            t += 10.0
        for y in np.arange(0.0, 601.0, 20.0):
            rows.append([t, y, 0.0])
            t += 1.0
    rows = np.asarray(rows)
    e = error_um(rows[:, 0], heat_j(rows[:, 0], copper_loss_w(rows[:, 2], 0.8, 0.0)), rows[:, 1], true)
    log = Log("a.csv", ["t_s", "pos_x_mm", "current_x_a", "err_x_um"], np.column_stack([rows, e]))
    res = fit_fa.fit(log, None, None, r_cu_ohm=0.8, length_mm=600, slide_volume_m3=volume_m3)
    assert res.model.params.eta == pytest.approx(0.25, rel=1e-3)
    assert res.report["eta_share"] == pytest.approx(0.25, rel=1e-3)
    assert res.report["eta_per_m3"] == pytest.approx(0.25 / volume_m3, rel=1e-3)
    # the same heat in an old file (η per m³, no volume) predicts the same error
    old = true.model_copy(update={"slide_volume_m3": None, "eta": 0.25 / volume_m3})
    assert np.allclose(
        error_um(rows[:, 0], heat_j(rows[:, 0], copper_loss_w(rows[:, 2], 0.8, 0.0)), rows[:, 1], old), e
    )


def test_numbered_columns_close_together_are_not_slide_positions():
    assert fit_fa._slide_by_name([f"T{i}" for i in range(1, 20)], 0.0, 600.0) is None
    found = fit_fa._slide_by_name(["T_motor", "T_slide_100mm", "T_slide_500mm", "T_amb"], 0.0, 600.0)
    assert found == [("T_slide_100mm", 100.0), ("T_slide_500mm", 500.0)]


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("T_base_000:0", "expected COL@MM"),
        ("T_base_000@zero", "expected COL@MM"),
        ("T_nope@10,T_base_150@150", "no column"),
        ("T_base_000@0,T_base_000@150", "each slide sensor"),
    ],
)
def test_bad_slide_sensors_option_is_one_line(value, says):
    with pytest.raises(BadInput, match=says) as e:
        fit_fa.fit(_field_log(hours=1.0), None, None, form="field", slide_sensors=value)
    assert "\n" not in str(e.value)


def test_field_form_without_slide_sensors_is_refused():
    log = _field_log(hours=1.0)
    keep = [c for c in log.columns if not c.startswith("T_base")]
    log = Log(log.file, keep, log.matrix(keep))
    with pytest.raises(BadInput, match="slide sensors"):
        fit_fa.fit(log, None, None, form="field")


def test_params_check_the_field_wiring():
    roles = ["position", "slide", "slide", "offset"]
    ok = FeedAxisParams(
        length_mm=600, input_roles=roles, field=SlideField(slide_mm=[0, 600], gain_integral=1.0, offset_um_per_k=[0.5])
    )
    assert ok.field is not None
    with pytest.raises(ValueError, match="slide_mm has 3 positions"):
        FeedAxisParams(
            length_mm=600,
            input_roles=roles,
            field=SlideField(slide_mm=[0, 300, 600], gain_integral=1.0, offset_um_per_k=[0.5]),
        )
    with pytest.raises(ValueError, match="strictly increasing"):
        SlideField(slide_mm=[300, 0], gain_integral=1.0)
    with pytest.raises(ValueError, match="analytic form needs"):
        FeedAxisParams(length_mm=600, input_roles=["position"], power_w=100.0)


def test_field_model_file_round_trips_and_a_config_accepts_it(tmp_path):
    from compd.commissioning.fitting import load_model, write_model

    log = _field_log(hours=2.0)
    model = fit_fa.fit(log, None, None, form="field", length_mm=L_MM, linear_p0_mm=300.0).model
    write_model(model, tmp_path / "m.yaml")
    back = load_model(tmp_path / "m.yaml")  # the analytic keys are written as null
    assert back.field_form and back.params == model.params
    X = log.matrix(back.inputs)
    assert np.allclose(back.predict(X, log.t_s), model.predict(X, log.t_s))


def test_position_poly_serves_a_log_whose_sensor_positions_are_unknown():
    # the same slide, its sensors named S1…S5 (no positions in the names)
    log = _field_log(noise_um=0.05)
    rename = {f"T_base_{int(s):03d}": f"S{k + 1}" for k, s in enumerate(SENSORS_MM)}
    log = Log(log.file, [rename.get(c, c) for c in log.columns], log.data)
    res = fit_fa.fit(log, None, None, length_mm=L_MM)
    assert res.report["form"] == "position_poly"
    sel = res.report["form_selection"]["held_out_rmse_um"]
    assert set(sel) == {"position_poly1", "position_poly2"}
    model = res.model
    X, t = log.matrix(model.inputs), log.t_s
    e = log.col("err_y_um")
    rmse = float(np.sqrt(np.mean((model.predict(X, t)[:, 0] - e) ** 2)))
    assert rmse < 0.1 * float(np.sqrt(np.mean(e**2)))  # > 90 % of the error explained
    # evaluate = predict, and the Siemens line from the same polynomial
    live = FeedAxis(model.params, model.inputs, model.outputs)
    live.start(X[0], t[0])
    out = np.zeros(1)
    for i in (10, 300, len(t) - 1):
        live.evaluate(X[i], t[i], out)
        assert out[0] == pytest.approx(model.predict(X[: i + 1], t[: i + 1])[i, 0], abs=1e-9)
    lin = FeedAxis(model.params.model_copy(update={"linear_p0_mm": 300.0}), model.inputs, model.outputs)
    lin.start(X[0], t[0])
    lin.evaluate(X[-1], t[-1], out)
    slope, _ = lin.linear_terms()[0]
    ys = np.linspace(0.0, L_MM, model.params.segments + 1)
    Xs = np.repeat(X[-1:], ys.size, axis=0)
    Xs[:, 0] = ys
    ref = FeedAxis(model.params, model.inputs, model.outputs)
    ref.start(X[0], t[0])
    k0_ref, slope_ref = np.polynomial.polynomial.polyfit(ys - 300.0, ref._field.predict(Xs), 1)
    assert out[0] == pytest.approx(k0_ref, abs=1e-9) and slope == pytest.approx(slope_ref, abs=1e-12)


def test_params_check_the_position_poly_wiring():
    from compd.models.feed_axis import PositionPoly

    with pytest.raises(ValueError, match="has 2 gains for degree 2"):
        PositionPoly(degree=2, coef_um_per_k=[[1.0, 2.0]])
    poly = PositionPoly(degree=1, coef_um_per_k=[[1.0, 2.0], [0.5, 0.0]])
    with pytest.raises(ValueError, match="one `rise` input per row"):
        FeedAxisParams(length_mm=600, input_roles=["position", "rise"], position_poly=poly)
    field = SlideField(slide_mm=[0, 600], gain_integral=1.0)
    with pytest.raises(ValueError, match="not both"):
        FeedAxisParams(length_mm=600, input_roles=["position", "rise", "rise"], position_poly=poly, field=field)

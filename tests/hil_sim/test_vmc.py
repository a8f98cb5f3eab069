"""The VMC plant (hil_sim.plants.vmc): two heat sources on one axis, their parts, sensors, unplugging, family."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.commissioning.fitting import fit_model
from compd.core.config import GuardConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.cycle.guard import Guard
from compd.log import error_axis, is_axis_error, is_temperature_column, read_log
from compd.sources import SOURCES
from hil_sim import family
from hil_sim.__main__ import main
from hil_sim.devices.plant import PlantDevice
from hil_sim.logcmd import run_log
from hil_sim.plants import PLANTS
from hil_sim.scenario import Scenario

SCENARIOS = Path(__file__).resolve().parents[2] / "hil_sim" / "scenarios"
QUIET = {"noise_c": 0.0, "resolution_c": 0.0, "tolerance": False, "drift_sensor": None}
SENSORS = ["T_xi", "T_amb", "T_brg_front", "T_brg_rear", "T_coolant", "T_col_top", "T_col_bot"]
COLUMNS = ["t_s", *SENSORS, "speed_rpm", "err_z_um_spindle", "err_z_um_column", "err_z_um"]
ALPHA_H_UM_PER_K = 11.5e-6 * 600.0 * 1000.0  # the column: α_c H, 6.9 µm per K of mean rise
ALPHA_L_UM_PER_K = 13.6e-6 * 165.0 * 1000.0  # the rotor: α_r L, 2.244 µm per K


def vmc(segments: list[dict], ambient: dict | None = None, **params: object):
    sc = Scenario.from_dict({"segments": segments, "seed": 5, "ambient": ambient or {"start_c": 20.0}})
    return PLANTS.get("vmc")(sc, {"dt_s": 10.0, **QUIET, **params})


def trace(plant, hours: float, step_s: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """Times (h) and rows [spindle part, column part, housing mean rise, column mean rise, T_col_top, T_col_bot]."""
    t = np.arange(step_s, hours * 3600.0 + 1.0, step_s)
    rows = []
    for x in t:
        plant.advance_to(x)
        temps = plant.true_temperatures_c()
        rows.append(
            [
                plant.spindle_um(),
                plant.column_um(),
                plant.net.rise("housing").mean(),
                plant.net.rise("column").mean(),
                temps[5],
                temps[6],
            ]
        )
    return t / 3600.0, np.array(rows)


def t63_h(t_h: np.ndarray, y: np.ndarray) -> float:
    """When |y| first reaches 63 % of its last value (a first-order body's time constant)."""
    return float(t_h[np.argmax(np.abs(y) >= (1.0 - math.exp(-1.0)) * abs(y[-1]))])


def test_log_command_writes_the_columns_compd_reads_as_meant(tmp_path, capsys):
    out = tmp_path / "train.csv"
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / "vmc_train.yaml"),
                "--out",
                str(out),
                "--duration-s",
                "14400",
                "--rate-s",
                "60",
            ]
        )
        == 0
    )
    assert "241 rows (vmc, 4.00 h simulated" in capsys.readouterr().out
    log = read_log(out)
    assert log.columns == COLUMNS
    # the parts are truth for tests: neither a temperature nor an axis's error to compd
    assert log.temperature_columns() == SENSORS
    assert log.error_columns() == ["err_z_um"]
    for part in ("err_z_um_spindle", "err_z_um_column"):
        # ... but each names its axis: a stage's target for z (compd fit --target err_z_um_spindle)
        assert not is_temperature_column(part) and not is_axis_error(part) and error_axis(part) == "z"
    # the error is its two parts (to the log's six significant digits)
    parts = log.col("err_z_um_spindle") + log.col("err_z_um_column")
    np.testing.assert_allclose(log.col("err_z_um"), parts, rtol=0, atol=1e-5 * np.abs(parts).max() + 1e-9)
    assert np.abs(log.col("err_z_um")).max() > 5.0
    assert np.allclose(log.matrix(SENSORS) * 10, np.round(log.matrix(SENSORS) * 10), atol=1e-6)  # 0.1 °C


def test_the_error_is_the_sum_of_the_spindle_and_the_column():
    p = vmc([{"duration_s": 7200, "speed_rpm": 12000}], {"start_c": 20.0, "hvac_amplitude_c": 0.3})
    for t in (600.0, 3600.0, 7200.0):
        p.advance_to(t)
        row = p.true_row()
        names = p.signal_names
        sp, col, err = (row[names.index(n)] for n in ("err_z_um_spindle", "err_z_um_column", "err_z_um"))
        assert err == pytest.approx(sp + col, abs=1e-12)
        assert sp == pytest.approx(p.axial_um() + p.lift_um(), abs=1e-12)  # the spindle plant's axial error
    assert p.axes == ("z",) and sp > 10.0 and col < 0.0


def test_the_spindle_part_is_fast_and_the_column_part_slow():
    t, r = trace(vmc([{"duration_s": 16 * 3600, "speed_rpm": 10000}]), 16.0)
    sp, col = r[:, 0], r[:, 1]
    assert sp[-1] > 15.0 and col[-1] < -2.0  # the spindle pushes the tool down, the column lifts the head
    assert t63_h(t, sp) < 1.0
    assert t63_h(t, col) > 2.5
    assert t63_h(t, col) > 3.0 * t63_h(t, sp)


def test_the_column_follows_the_ambient_while_the_spindle_stands():
    """+1 K in the hall, spindle off: each part settles to its own α·length, the column far later."""
    t, r = trace(vmc([{"duration_s": 16 * 3600}], {"start_c": 20.0, "points": [[0, 0.0], [0.01, 1.0]]}), 16.0)
    sp, col = r[:, 0], r[:, 1]
    assert col[-1] == pytest.approx(-ALPHA_H_UM_PER_K, rel=0.02)
    assert sp[-1] == pytest.approx(ALPHA_L_UM_PER_K, rel=0.02)
    assert t63_h(t, col) > 2.0 > 1.0 > t63_h(t, sp)
    assert r[-1, 4] == pytest.approx(21.0, abs=0.02) and r[-1, 5] == pytest.approx(21.0, abs=0.02)
    one_hour = int(np.argmin(np.abs(t - 1.0)))
    assert abs(col[one_hour]) < 0.5 * abs(col[-1])  # an hour in, the column has not half followed


def test_the_spindle_warms_the_column_a_little():
    idle = vmc([{"duration_s": 8 * 3600}])
    idle.advance_to(8 * 3600)
    assert abs(idle.column_um()) < 1e-9 and abs(idle.spindle_um()) < 1e-9  # nothing moves it
    _, dry = trace(vmc([{"duration_s": 8 * 3600, "speed_rpm": 10000}]), 8.0)
    _, wet = trace(vmc([{"duration_s": 8 * 3600, "speed_rpm": 10000, "coolant": True}]), 8.0)
    housing, column = dry[-1, 2], dry[-1, 3]
    assert 0.2 < column < 2.0 and housing > 5.0 * column  # a little, through the headstock
    assert dry[-1, 4] - 20.0 > 2.0 * (dry[-1, 5] - 20.0) > 0.0  # it enters near the top
    assert -15.0 < dry[-1, 1] < -1.0
    assert wet[-1, 3] < 0.2 * column  # the coolant takes the housing's heat away


@pytest.fixture(scope="module")
def training_log(tmp_path_factory: pytest.TempPathFactory):
    sc = Scenario.load(SCENARIOS / "vmc_train.yaml")
    out = tmp_path_factory.mktemp("vmc") / "train.csv"
    run_log(PLANTS.get("vmc")(sc, {"dt_s": 10.0}), out, 60.0)
    return read_log(out)


def test_the_spindle_sensor_alone_leaves_what_the_column_sensors_explain(training_log):
    log = training_log
    err, column = log.col("err_z_um"), log.col("err_z_um_column")
    alone = fit_model("mlr", log, ["T_xi"], ["err_z_um"], {}, baseline=False)
    resid = err - alone.pred[:, 0]
    rms_alone = float(np.sqrt(np.mean(resid**2)))
    assert rms_alone > 2.0
    assert np.corrcoef(resid, column)[0, 1] > 0.6  # the residual is the column's, not noise
    # least squares of that residual on the column sensors' rises: most of it goes
    rises = log.matrix(["T_col_top", "T_col_bot"]) - log.matrix(["T_col_top", "T_col_bot"])[0]
    a = np.column_stack([np.ones(len(log)), rises])
    left = resid - a @ np.linalg.lstsq(a, resid, rcond=None)[0]
    assert np.var(left) < 0.4 * np.var(resid)
    both = fit_model("mlr", log, ["T_xi", "T_col_top", "T_col_bot"], ["err_z_um"], {}, baseline=False)
    rms_both = float(np.sqrt(np.mean((err - both.pred[:, 0]) ** 2)))
    assert rms_both < 0.35 * rms_alone
    coef = np.asarray(both.model.params.coef_um_per_k)[:, 0]
    assert coef[0] == pytest.approx(ALPHA_L_UM_PER_K, rel=0.3)  # T_xi: the rotor's α L
    assert coef[1] + coef[2] == pytest.approx(-ALPHA_H_UM_PER_K, rel=0.3)  # the column: −α_c H


def test_each_part_is_read_by_its_own_sensors(training_log):
    """The column sensors explain the column's part, not the spindle's; T_xi the other way round."""
    log = training_log

    def rms_left(target: str, inputs: list[str]) -> float:
        y = log.col(target)
        x = log.matrix(inputs) - log.matrix(inputs)[0]
        a = np.column_stack([np.ones(len(log)), x])
        return float(np.sqrt(np.mean((y - a @ np.linalg.lstsq(a, y, rcond=None)[0]) ** 2)))

    col, sp = ("err_z_um_column", "err_z_um_spindle")
    assert rms_left(col, ["T_col_top", "T_col_bot"]) < 0.25 * rms_left(col, ["T_xi"])
    assert rms_left(sp, ["T_xi"]) < 0.5 * rms_left(sp, ["T_col_top", "T_col_bot"])


def test_shipped_days_show_both_time_constants():
    days = {d: Scenario.load(SCENARIOS / f"vmc_{d}.yaml") for d in ("train", "unseen")}
    speeds = {}
    for day, sc in days.items():
        assert sc.machine == "vmc" and sc.duration_s == pytest.approx(86400.0)
        runs = [s for s in sc.segments if s.speed_rpm > 0]
        speeds[day] = {s.speed_rpm for s in runs}
        assert len(speeds[day]) >= 3
        assert any(s.coolant for s in runs) and any(not s.coolant for s in runs)  # the coupling shows dry
        # a stop of ≥ 2 h before the night while the hall moves by ≥ 1 K: the column alone
        ends = sc.boundaries()
        night = len(sc.segments) - 1
        assert any(
            s.speed_rpm == 0
            and s.duration_s >= 7200
            and abs(sc.ambient.at(ends[k + 1]) - sc.ambient.at(ends[k])) >= 1.0
            for k, s in enumerate(sc.segments[:night])
        ), day
    assert speeds["unseen"] - speeds["train"]  # speeds the training never ran


def _unplug_file(tmp_path: Path, unplug: dict | None) -> Path:
    doc = {"machine": "vmc", "seed": 3, "params": {"dt_s": 10.0}, "segments": [{"duration_s": 7200, "speed_rpm": 8000}]}
    if unplug is not None:
        doc["params"]["sensor_unplug_s"] = unplug
    f = tmp_path / f"unplug_{unplug is not None}.yaml"
    f.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return f


def test_a_scenario_entry_unplugs_a_sensor_mid_day(tmp_path):
    logs = {}
    for unplug in (None, {"T_col_top": 3600, "T_xi": [1800, 2700]}):
        out = tmp_path / f"{unplug is not None}.csv"
        assert (
            main(["log", "--scenario", str(_unplug_file(tmp_path, unplug)), "--out", str(out), "--rate-s", "60"]) == 0
        )
        logs[unplug is not None] = out
    with pytest.raises(BadInput, match="not a finite number"):
        read_log(logs[True])  # a reader that takes no missing values refuses it
    plugged, log = read_log(logs[False]), read_log(logs[True], allow_nan=True)
    t = log.t_s
    top, xi = log.col("T_col_top"), log.col("T_xi")
    assert np.all(np.isnan(top[t >= 3600])) and np.all(np.isfinite(top[t < 3600]))
    off = (t >= 1800) & (t < 2700)
    assert np.all(np.isnan(xi[off])) and np.all(np.isfinite(xi[~off]))  # plugged in again
    # everything else as if nothing were unplugged: the same readings, the same errors
    keep = np.isfinite(log.data)
    assert keep.sum() == log.data.size - (t >= 3600).sum() - off.sum()
    np.testing.assert_array_equal(log.data[keep], plugged.data[keep])


def test_the_sim_source_publishes_an_unplugged_sensor_as_a_fault():
    cls = SOURCES.get("sim")  # compd finds it through hil_sim's entry point
    cfg = cls.Config(
        kind="sim",
        name="vmc",
        plant="vmc",
        params={"sensor_unplug_s": {"T_col_top": 600}},
        scenario={"segments": [{"duration_s": 3600, "speed_rpm": 10000}], "seed": 4},
    )
    src = cls(cfg)
    assert src.signal_names() == COLUMNS[1:]
    frame = Frame(src.signal_names())
    src.bind(frame)
    guard = Guard(GuardConfig(), ["z"], frame, ["T_xi", "T_col_top"])
    top = frame.index["T_col_top"]
    src.read(frame, 300.0)
    assert guard.check_inputs(frame, 300.0) and math.isfinite(frame.values[top])
    src.read(frame, 900.0)
    assert math.isnan(frame.values[top])
    assert not guard.check_inputs(frame, 900.0)
    assert frame.quality[top] == Quality.IMPLAUSIBLE and frame.quality[frame.index["T_xi"]] == Quality.GOOD
    v = dict(zip(frame.names, frame.values, strict=True))
    assert v["err_z_um"] == pytest.approx(v["err_z_um_spindle"] + v["err_z_um_column"], abs=1e-9)


def test_the_served_plant_publishes_the_parts_and_the_unplugged_sensor():
    sc = Scenario.from_dict(
        {
            "segments": [{"duration_s": 7200, "speed_rpm": 9000}],
            "seed": 2,
            "params": {"dt_s": 5.0, "sensor_unplug_s": {"T_xi": 1800}},
        }
    )
    dev = PlantDevice(PLANTS.get("vmc")(sc, sc.params), lockstep=True)
    feed = dev.feed_for(["T_xi", "T_col_bot", "err_z_um_spindle", "err_z_um_column", "err_z_um"])
    dev.run_to(1200.0)
    before = feed()
    dev.run_to(3600.0)
    after = feed()
    assert math.isfinite(before[0]) and math.isnan(after[0]) and math.isfinite(after[1])
    assert after[4] == pytest.approx(after[2] + after[3], abs=1e-6) and after[2] > before[2] > 0.0


@pytest.mark.parametrize(
    ("params", "says"),
    [
        ({"sensor_unplug_s": {"T_col_mid": 100}}, "sensor_unplug_s.T_col_mid: not a sensor"),
        ({"sensor_unplug_s": {"T_xi": [500, 200]}}, "sensor_unplug_s.T_xi: a time"),
        ({"sensor_unplug_s": {"T_xi": -1}}, "sensor_unplug_s.T_xi: a time"),
        ({"sensor_unplug_s": {"T_xi": True}}, "sensor_unplug_s.T_xi: a time"),
        ({"sensor_unplug_s": [1, 2]}, "sensor_unplug_s: a mapping"),
        ({"column_top_sensor_mm": 700.0}, "column_top_sensor_mm: on the column"),
        ({"column_nodes": 1}, "column_nodes: an integer >= 2"),
        ({"column_h_w_m2k": 0.0}, "column_h_w_m2k: must be > 0"),
    ],
)
def test_bad_params_are_named(params, says):
    with pytest.raises(ValueError, match=says):
        vmc([{"duration_s": 60}], **params)


def test_bad_params_in_a_scenario_file_exit_2(tmp_path, capsys):
    f = tmp_path / "bad.yaml"
    f.write_text("machine: vmc\nparams: {sensor_unplug_s: {T_col: 10}}\nsegments: [{duration_s: 60}]\n")
    assert main(["log", "--scenario", str(f), "--out", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "T_col: not a sensor" in err


def test_the_column_sensors_take_the_common_sensor_model():
    """Lag and cross-talk (hil_sim.plants.base) on a column sensor, a column point as the neighbour."""
    amb = {"start_c": 20.0, "points": [[0, 0.0], [0.01, 2.0]]}
    p = vmc(
        [{"duration_s": 7200}],
        amb,
        sensor_lag_s={"T_col_bot": 1800.0},
        sensor_crosstalk={"T_col_top": [0.5, "column@0"]},
    )
    p.advance_to(7200)
    true = p.true_temperatures_c()
    seen = p.sensor_temperatures_c()
    top, bot = SENSORS.index("T_col_top"), SENSORS.index("T_col_bot")
    assert seen[top] == pytest.approx(0.5 * true[top] + 0.5 * p.net.at("column", 0.0), abs=1e-9)
    assert 20.0 < seen[bot] < true[bot] - 0.05  # behind its point


def test_the_family_draws_vmc_machines(tmp_path):
    assert "vmc" in family.ALL_KINDS and "vmc" not in family.KINDS  # not yet in scripts/family.py
    defaults = PLANTS.get("vmc").DEFAULTS
    spindle = {"T_xi", "T_brg_front", "T_brg_rear", "T_coolant"}
    for seed in range(1, 6):
        m = family.draw("vmc", seed)
        for name, (how, lo, hi) in family.RANGES["vmc"].items():
            if how == "factor":
                assert lo * 0.999 <= m.params[name] / defaults[name] <= hi * 1.001, name
        height = m.params["column_height_mm"]
        assert 0 < m.params["column_bottom_sensor_mm"] < m.params["column_top_sensor_mm"] < height
        plant = m.plant("unseen")
        assert list(m.params["sensor_lag_s"]) == plant.sensor_names == SENSORS
        for sensor, (_, neighbour) in m.params.get("sensor_crosstalk", {}).items():
            # each source's sensors see only its own body
            assert (sensor in spindle) == (not neighbour.startswith("column@")), (sensor, neighbour)
        assert m.drawn["duty"]["coolant"] in (True, False)
    assert family.draw("vmc", 4).params == family.draw("vmc", 4).params != family.draw("vmc", 5).params
    summary = family.write_machine(family.draw("vmc", 2, day_h=2.0), tmp_path, 120.0)
    assert summary["train"]["z"]["rms_um"] > 1.0
    log = read_log(tmp_path / "vmc_2_train.csv")
    assert log.columns == COLUMNS
    np.testing.assert_allclose(log.col("err_z_um"), log.col("err_z_um_spindle") + log.col("err_z_um_column"), atol=1e-3)

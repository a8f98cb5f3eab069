"""Randomized machine families: hil_sim.family, the plants' sensor model, the HVAC cycle, the harness.

Also: placement (feed axis base sensors), the gantry's unmeasured column, the `hil_sim family`
command's bad input, and scripts/family.py on two short machines.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.log import read_log
from hil_sim import family
from hil_sim.__main__ import main
from hil_sim.logcmd import load_plant, run_log
from hil_sim.plants import PLANTS
from hil_sim.scenario import Ambient, Scenario, Segment

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "hil_sim" / "scenarios"

# sha256 of `python -m hil_sim log --scenario S --rate-s 30 --duration-s 14400` as written before
# the sensor model, the HVAC cycle, the feed axis's base sensor places and the gantry's column
# existed: their defaults must leave every existing log as it was, byte for byte. (A deliberate
# change of a plant's physics changes these: regenerate them with that command and sha256sum.)
GOLDEN = {
    "feed_axis_train": "b14eeb07bffad164a58a6458c4ddb72b1c1c2e9f8f043e8a2c039c68e294b639",
    "feed_axis_unseen": "236fd60392a700d09df13acf7b9235bb761e4610613df139dec9466a867e4f17",
    "gantry_train": "a1f3e38d2ca4f293cbc8320b5c1321a596f558f65030fc908e6678f5186a7518",
    "gantry_unseen": "3e10a0d54e6436a52dfafaa3c6c5b257b7a8e5eeb41618a492389fe8c5bb860f",
    "lathe_train": "855087119c134d9837d9b4a78ebe96fc3b03b566908dc041fc77607dce30d1f4",
    "lathe_unseen": "2c4fa33a891290aba9eeb84fbab87f72a4dbf370e0661445641fdbf87affcfea",
    "spindle_demo": "e2d53e25ec7f225cb9bad7f917348b36f4c654dbebda617d08a5d6cefdffe4ce",
    "spindle_train": "3e79c537ce11cee7c450d6efdd2414cd1b29f8fd0e5166070ad2103ce4774738",
    "spindle_unseen": "a6bded977e2d65ac72fa10bb7b346d6cd2dc11b54b8f0ea10efb04ac005e2259",
}


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_defaults_leave_every_existing_log_byte_identical(name, tmp_path):
    out = tmp_path / "log.csv"
    assert (
        main(
            [
                "log",
                "--scenario",
                str(SCENARIOS / f"{name}.yaml"),
                "--out",
                str(out),
                "--rate-s",
                "30",
                "--duration-s",
                "14400",
            ]
        )
        == 0
    )
    assert hashlib.sha256(out.read_bytes()).hexdigest() == GOLDEN[name]


@pytest.mark.parametrize("machine", ["lathe", "spindle", "gantry", "feed_axis"])
def test_features_switched_off_explicitly_change_nothing(machine, tmp_path):
    """sensor_lag_s 0, no cross-talk, HVAC amplitude 0, no column, no shifts: the default's bytes."""
    base = load_plant(str(SCENARIOS / f"{machine}_unseen.yaml"))
    sc = Scenario.load(SCENARIOS / f"{machine}_unseen.yaml")
    sc.ambient = Ambient(
        **{
            **{
                k: getattr(sc.ambient, k)
                for k in ("start_c", "drift_c_per_h", "daily_amplitude_c", "daily_phase_h", "points")
            },
            "hvac_amplitude_c": 0.0,
            "hvac_period_s": 900.0,
            "hvac_shape": "square",
        }
    )
    extra = {"sensor_lag_s": 0.0, "sensor_crosstalk": {}}
    if machine == "gantry":
        extra["column_cap_j_k"] = 0.0
    if machine == "feed_axis":
        extra["base_sensor_shift_mm"] = [0.0] * 5
    off = PLANTS.get(machine)(sc, {**sc.params, **extra})
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    run_log(base, a, 60.0, 7200.0)
    run_log(off, b, 60.0, 7200.0)
    assert a.read_bytes() == b.read_bytes()


# --- the sensor model ------------------------------------------------------------------
def _ambient_step_lathe(params: dict) -> object:
    """A lathe standing still while its shop steps 1 K warmer at t = 3600 s: T7 (the air) steps."""
    sc = Scenario([Segment(7200.0)], Ambient(start_c=20.0, points=[[0, 0.0], [1, 0.0], [1, 1.0]]), seed=1)
    quiet = {"noise_c": 0.0, "resolution_c": 0.0, "tolerance": False, "drift_sensor": None}
    return PLANTS.get("lathe")(sc, {**quiet, **params})


@pytest.mark.parametrize("dt_s", [1.0, 10.0])
def test_sensor_lag_reaches_63_percent_of_a_step_at_its_time_constant(dt_s):
    p = _ambient_step_lathe({"sensor_lag_s": {"T7": 100.0}, "dt_s": dt_s})
    p.advance_to(3600.0)
    assert p.sensor_temperatures_c()[6] == pytest.approx(20.0, abs=1e-12)
    assert p.true_temperatures_c()[6] == pytest.approx(21.0)  # the air itself has stepped
    p.advance_to(3700.0)
    assert p.sensor_temperatures_c()[6] - 20.0 == pytest.approx(1.0 - math.exp(-1.0), abs=1e-9)
    p.advance_to(4100.0)
    assert p.sensor_temperatures_c()[6] - 20.0 == pytest.approx(1.0 - math.exp(-5.0), abs=1e-9)
    # the other sensors have no lag here: they read their points
    np.testing.assert_array_equal(p.sensor_temperatures_c()[:6], p.true_temperatures_c()[:6])


def test_sensor_lag_one_number_lags_every_sensor_and_reaches_the_log(tmp_path):
    fast = _ambient_step_lathe({})
    slow = _ambient_step_lathe({"sensor_lag_s": 300.0})
    assert slow._lag is not None and np.all(slow._lag.lag_s == 300.0)
    times = np.arange(0.0, 7201.0, 60.0)
    a, b = fast.record(times), slow.record(times)
    k = int(np.searchsorted(times, 3660.0))
    assert a[k, 6] == pytest.approx(21.0)
    assert b[k, 6] == pytest.approx(20.0 + 1.0 - math.exp(-60.0 / 300.0), abs=1e-9)
    np.testing.assert_array_equal(a[:, -1], b[:, -1])  # the true error does not depend on the sensors
    # and `sample()`, what the sim source and the served plant read
    s = _ambient_step_lathe({"sensor_lag_s": 300.0})
    s.advance_to(3660.0)
    assert s.sample()[6] == pytest.approx(b[k, 6], abs=1e-12)


def test_the_served_plant_publishes_the_lagged_elements():
    from hil_sim.devices.plant import PlantDevice

    dev = PlantDevice(_ambient_step_lathe({"sensor_lag_s": {"T7": 100.0}}), lockstep=True)
    t7 = dev.feed_for(["T7"])
    dev.run_to(3700.0)
    assert t7()[0] == pytest.approx(20.0 + 1.0 - math.exp(-1.0), abs=1e-9)


def _warm_lathe(params: dict) -> object:
    sc = Scenario([Segment(4000.0, speed_rpm=2500.0)], Ambient(start_c=20.0), seed=2)
    quiet = {"noise_c": 0.0, "resolution_c": 0.0, "tolerance": False, "drift_sensor": None}
    p = PLANTS.get("lathe")(sc, {**quiet, **params})
    p.advance_to(3600.0)
    return p


def test_crosstalk_blends_a_neighbouring_sensor_or_a_point_of_the_structure():
    p = _warm_lathe({"sensor_crosstalk": {"T1": [0.25, "T2"], "T3": [0.2, "bed@1500"], "T2": [0.1, "saddle"]}})
    true = p.true_temperatures_c()
    got = p.sensor_temperatures_c()
    assert got[0] == pytest.approx(0.75 * true[0] + 0.25 * true[1])
    assert got[2] == pytest.approx(0.8 * true[2] + 0.2 * p.net.at("bed", 1.5))
    assert got[1] == pytest.approx(0.9 * true[1] + 0.1 * p.net.T[p.saddle])
    np.testing.assert_array_equal(got[3:], true[3:])
    assert abs(got[0] - true[0]) > 0.01  # the headstock is not uniform after an hour at speed


def test_crosstalk_and_lag_together_lag_the_blend():
    p = _warm_lathe({"sensor_crosstalk": {"T1": [0.3, "spindle@50"]}, "sensor_lag_s": {"T1": 1e9}})
    assert p.sensor_temperatures_c()[0] == pytest.approx(20.0, abs=1e-4)  # an element that never follows


@pytest.mark.parametrize(
    "params, says",
    [
        ({"sensor_crosstalk": {"T9": [0.1, "T1"]}}, "not a sensor"),
        ({"sensor_crosstalk": {"T1": [1.0, "T2"]}}, "[0, 1)"),
        ({"sensor_crosstalk": {"T1": [0.1, "casting"]}}, "neither a sensor nor a body"),
        ({"sensor_crosstalk": {"T1": [0.1, "bed"]}}, "is a rod"),
        ({"sensor_crosstalk": {"T1": [0.1, "saddle@10"]}}, "lumped body"),
        ({"sensor_crosstalk": {"T1": 0.1}}, "[fraction, neighbour]"),
        ({"sensor_lag_s": -1.0}, ">= 0"),
        ({"sensor_lag_s": {"T8": 3.0}}, "not a sensor"),
        ({"sensor_lag_s": "slow"}, "seconds"),
    ],
)
def test_sensor_model_params_are_checked(params, says):
    with pytest.raises(ValueError, match=None) as e:
        _warm_lathe(params)
    assert says in str(e.value)


# --- placement and unmeasured parts ----------------------------------------------------
def test_feed_axis_base_sensors_keep_their_nominal_names_where_they_are_moved():
    sc = Scenario([Segment(3600.0, feed_mm_min=6000.0)], seed=3)
    quiet = {"noise_c": 0.0, "resolution_c": 0.0, "tolerance": False, "drift_sensor": None}
    params = {
        "stroke_mm": [0.0, 1000.0],
        "base_length_mm": 1200.0,
        "base_nodes": 60,
        "base_sensors_mm": [0.0, 250.0, 500.0, 750.0, 1000.0],
        "base_sensor_shift_mm": [5.0, -30.0, 0.0, 30.0, -10.0],
    }
    p = PLANTS.get("feed_axis")(sc, {**quiet, **params})
    assert p.sensor_names[4:9] == ["T_base_000", "T_base_250", "T_base_500", "T_base_750", "T_base_1000"]
    p.advance_to(3600.0)
    got = p.sensor_temperatures_c()
    for k, (y, s) in enumerate(zip(params["base_sensors_mm"], params["base_sensor_shift_mm"], strict=True)):
        assert got[4 + k] == pytest.approx(p.net.at("y.base", (100.0 + y + s) / 1000.0))
    with pytest.raises(ValueError, match="one shift per base sensor"):
        PLANTS.get("feed_axis")(sc, {**params, "base_sensor_shift_mm": [1.0]})


def test_gantry_column_grows_unseen():
    sc = Scenario([Segment(7200.0, feed_mm_min=2000.0)], seed=4)
    bare = PLANTS.get("gantry")(sc)
    col = PLANTS.get("gantry")(sc, {"column_cap_j_k": 40000.0, "column_lever_mm": 300.0})
    assert col.sensor_names == bare.sensor_names  # no sensor on it
    for p in (bare, col):
        p.advance_to(7200.0)
    rise = col.net.T[col.columns] - col.net.T_init[col.columns]
    assert np.all(rise > 0.05)
    # the same network less the column differs, so compare with the column's own term only
    expected = np.array([s.error_here_um() for s in col.sides]) + 11.5e-6 * 0.3 * 1e6 * rise
    np.testing.assert_allclose(col.true_error_um(), expected)
    np.testing.assert_allclose(
        col.error_profile_um()[:, 0] - np.array([s.error_um(20.0)[0] for s in col.sides]), 11.5e-6 * 0.3 * 1e6 * rise
    )


# --- the ambient's HVAC cycle -----------------------------------------------------------
@pytest.mark.parametrize(
    "shape, at_quarter, at_three_quarters", [("sine", 1.0, -1.0), ("square", 1.0, -1.0), ("triangle", -0.0, 0.0)]
)
def test_hvac_cycle_shapes(shape, at_quarter, at_three_quarters):
    amb = Ambient(start_c=20.0, hvac_amplitude_c=0.4, hvac_period_s=1200.0, hvac_shape=shape)
    assert amb.at(300.0) == pytest.approx(20.0 + 0.4 * at_quarter)
    assert amb.at(900.0) == pytest.approx(20.0 + 0.4 * at_three_quarters)
    assert amb.at(300.0 + 5 * 1200.0) == pytest.approx(amb.at(300.0))
    vals = [amb.at(t) for t in np.arange(0.0, 2400.0, 7.0)]
    assert max(vals) <= 20.4 + 1e-12 and min(vals) >= 19.6 - 1e-12


def test_hvac_keys_in_scenario_files_and_round_trip():
    sc = Scenario.from_dict(
        {
            "machine": "lathe",
            "seed": 3,
            "ambient": {"start_c": 19.0, "hvac_amplitude_c": 0.2, "hvac_period_s": 1800, "hvac_shape": "triangle"},
            "segments": [
                {"duration_s": 60, "speed_rpm": 1000, "load": 1.1},
                {"duration_s": 60, "feed_mm_min": 10, "stroke_mm": [0, 5]},
            ],
        }
    )
    again = Scenario.from_dict(sc.to_dict())
    assert again.segments == sc.segments and again.ambient == sc.ambient and again.seed == 3
    with pytest.raises(ValueError, match="hvac_shape"):
        Scenario.from_dict({"ambient": {"hvac_shape": "wobble"}, "segments": [{"duration_s": 1}]})
    with pytest.raises(ValueError, match="hvac_period_s"):
        Scenario.from_dict({"ambient": {"hvac_period_s": 0}, "segments": [{"duration_s": 1}]})


# --- the family ---------------------------------------------------------------------------
@pytest.mark.parametrize("kind", family.KINDS)
def test_same_seed_same_machine_and_logs(kind, tmp_path):
    a, b, c = (tmp_path / n for n in "abc")
    for d, seed in ((a, 4), (b, 4), (c, 5)):
        d.mkdir()
        family.write_machine(family.draw(kind, seed, day_h=1.0), d, 120.0)
    for suffix in ("train.csv", "unseen.csv", "machine.yaml"):
        assert (a / f"{kind}_4_{suffix}").read_bytes() == (b / f"{kind}_4_{suffix}").read_bytes()
    assert (a / f"{kind}_4_unseen.csv").read_bytes() != (c / f"{kind}_5_unseen.csv").read_bytes()
    assert family.draw(kind, 4).params == family.draw(kind, 4).params
    assert family.draw(kind, 4).params != family.draw(kind, 5).params


@pytest.mark.parametrize("kind", family.KINDS)
def test_draws_stay_in_their_ranges(kind):
    defaults = PLANTS.get(kind).DEFAULTS
    for seed in range(1, 9):
        m = family.draw(kind, seed)
        for name, (how, lo, hi) in family.RANGES[kind].items():
            v, d = m.params[name], defaults[name]
            if how == "factor":
                f = (v[0] / d[0]) if isinstance(d, list) else v / d
                assert lo * 0.999 <= f <= hi * 1.001, (name, f)
            else:
                assert lo <= v <= hi, (name, v)
        lags = m.params["sensor_lag_s"]
        amb = family.AMBIENT_SENSOR[kind]
        assert 1.0 <= lags[amb] <= 20.0 * 1.001
        assert all(1.0 * 0.999 <= v <= 300.0 * 1.001 for v in lags.values())
        for sensor, (frac, _) in m.params.get("sensor_crosstalk", {}).items():
            assert sensor != amb and 0.0 < frac <= 0.3
        plant = m.plant("unseen")  # builds: names and neighbours are the plant's
        assert list(lags) == plant.sensor_names
        for sc in (m.train, m.unseen):
            assert sc.duration_s == family.DAY_S
            assert sc.segments[-1].speed_rpm == 0 and sc.segments[-1].feed_mm_min == 0  # the night
        duty = m.drawn["duty"]
        lo_lim, hi_lim = family.DUTY[kind]["limits"]
        assert 1 <= len(duty["train_levels"]) <= 2
        assert min(duty["unseen_levels"]) < min(duty["train_levels"]) or min(duty["train_levels"]) == lo_lim
        assert max(duty["unseen_levels"]) > max(duty["train_levels"]) or max(duty["train_levels"]) == hi_lim
        loads = [s.load for s in m.unseen.segments if s.speed_rpm > 0 or s.feed_mm_min > 0]
        assert all(0.8 <= x <= 1.3 for x in loads) and len(set(loads)) > 1
        start = m.train.ambient.start_c - m.unseen.ambient.start_c
        assert abs(start) <= 2.0 + 1e-9
        for amb_day in (m.train.ambient, m.unseen.ambient):
            assert 0.1 <= amb_day.hvac_amplitude_c <= 0.5 and 900 <= amb_day.hvac_period_s <= 3600
            assert abs(amb_day.drift_c_per_h * 24.0) <= 1.0 + 1e-3


def test_kind_specific_draws():
    for seed in range(1, 9):
        f = family.draw("feed_axis", seed)
        stroke = f.params["stroke_mm"][1]
        assert 600.0 <= stroke <= 1200.0 and f.params["base_length_mm"] == stroke + 200.0
        assert all(abs(s) <= 30.0 for s in f.params["base_sensor_shift_mm"])
        runs = [s for s in f.unseen.segments if s.feed_mm_min > 0]
        partial = [s.stroke_mm for s in runs if tuple(s.stroke_mm) != (0.0, stroke)]
        assert partial and all(lo == 0.0 or hi == stroke for lo, hi in partial)  # at one end
        assert tuple(runs[0].stroke_mm) != (0.0, stroke)
        s = family.draw("spindle", seed)
        place = s.drawn["placement"]
        assert abs(place["xi_mm"] - place["xi_mean_value_point_mm"]) <= 0.2 * s.params["length_mm"] + 0.1
        lathe = family.draw("lathe", seed)
        assert lathe.params["saddle_x_mm"] > lathe.params["spindle_length_mm"]
    columns = [family.draw("gantry", seed).drawn["placement"]["column"] for seed in range(1, 21)]
    assert 0 < sum(columns) < 20  # some gantries carry an unmeasured column, some not
    full_only = [family.draw("gantry", seed).drawn["duty"]["train_partial_strokes"] == 0 for seed in range(1, 21)]
    assert 0 < sum(full_only) < 20  # some training days have only full strokes


def test_machine_file_reruns_a_day(tmp_path):
    m = family.draw("spindle", 2, day_h=2.0)
    family.write_machine(m, tmp_path, 30.0)
    doc = yaml.safe_load((tmp_path / "spindle_2_machine.yaml").read_text())
    assert doc["kind"] == "spindle" and doc["seed"] == 2 and doc["log_rate_s"] == 30.0
    assert set(doc["errors_um"]) == {"train", "unseen"}
    (tmp_path / "day.yaml").write_text(yaml.safe_dump(doc["unseen"]))
    assert (
        main(["log", "--scenario", str(tmp_path / "day.yaml"), "--out", str(tmp_path / "again.csv"), "--rate-s", "30"])
        == 0
    )
    assert (tmp_path / "again.csv").read_bytes() == (tmp_path / "spindle_2_unseen.csv").read_bytes()


@pytest.mark.slow
def test_family_command_writes_the_files(tmp_path, capsys):
    assert main(["family", "--kind", "lathe", "--seeds", "3,5", "--out", str(tmp_path / "f"), "--rate-s", "600"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and "lathe_3" in out[0] and "working" in out[0]
    names = sorted(p.name for p in (tmp_path / "f").iterdir())
    assert names == [f"lathe_{s}_{x}" for s in (3, 5) for x in ("machine.yaml", "train.csv", "unseen.csv")]
    log = read_log(tmp_path / "f" / "lathe_5_unseen.csv")
    assert log.columns == ["t_s", "T1", "T2", "T3", "T4", "T5", "T6", "T7", "speed_rpm", "err_z_um"]
    assert len(log) == 145


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--kind", "mill", "--seeds", "1", "--out", "{o}"], "unknown kind 'mill'"),
        (["--kind", "lathe", "--seeds", "5-2", "--out", "{o}"], "--seeds"),
        (["--kind", "lathe", "--seeds", "x", "--out", "{o}"], "--seeds"),
        (["--kind", "lathe", "--seeds", "-3", "--out", "{o}"], "--seeds"),
        (["--kind", "lathe", "--seeds", "1", "--out", "{o}", "--rate-s", "0"], "--rate-s"),
        (["--kind", "lathe", "--seeds", "1", "--out", "{o}", "--rate-s", "fast"], "--rate-s"),
        (["--kind", "lathe", "--seeds", "1", "--out", "{o}", "--bogus", "1"], "--bogus"),
        (["--kind", "lathe", "--out", "{o}"], "--seeds"),
    ],
)
def test_family_command_bad_input_one_line_exit_2(argv, says, tmp_path, capsys):
    out = tmp_path / "o"
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(["family", *(a.format(o=out) for a in argv)]))
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert says in err
    assert not out.exists() or not any(out.iterdir())  # nothing written


def test_family_command_unwritable_folder(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["family", "--kind", "lathe", "--seeds", "1", "--out", str(blocker / "sub")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


# --- the harness -----------------------------------------------------------------------
def _harness():
    """scripts/family.py as a module (registered, so its worker processes find its functions)."""
    if "family_harness" in sys.modules:
        return sys.modules["family_harness"]
    spec = importlib.util.spec_from_file_location("family_harness", ROOT / "scripts" / "family.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["family_harness"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_probes_every_h_hours_on_the_true_error():
    h = _harness()
    from compd.log import Log

    t = np.arange(0.0, 7 * 3600.0 + 1, 60.0)
    log = Log("x.csv", ["t_s", "pos_y_mm", "err_y_um"], np.column_stack([t, t / 100.0, np.sin(t / 5000.0) * 10]))
    p = h.with_probes(log, ["y"], 2 * 3600.0, np.random.default_rng(0))
    z = p.col("probe_y_um")
    rows = np.flatnonzero(np.isfinite(z))
    np.testing.assert_array_equal(t[rows], [7200.0, 14400.0, 21600.0])
    assert np.all(np.abs(z[rows] - log.col("err_y_um")[rows]) < 5 * 0.3)
    np.testing.assert_array_equal(p.col("probe_pos_y_mm")[rows], log.col("pos_y_mm")[rows])


def test_harness_on_two_short_machines(tmp_path, capsys):
    """Two lathes on 4 h days: logs, fits, replays with and without probes, the table and the JSON;
    the logs are reused while the drawn machine is the same."""
    h = _harness()
    out = tmp_path / "r.json"
    args = [
        "--kinds",
        "lathe",
        "--seeds",
        "1-2",
        "--day-h",
        "4",
        "--workdir",
        str(tmp_path / "w"),
        "--json",
        str(out),
        "--jobs",
        "2",
        "--probe-every-h",
        "1",
    ]
    assert h.main(args) == 0
    text = capsys.readouterr().out
    assert "| type | axis | model | median | 10th pct | worst | MLR median | MLR better on |" in text
    doc = json.loads(out.read_text())
    assert [m["seed"] for m in doc["machines"]] == [1, 2]
    for m in doc["machines"]:
        assert set(m["models"]) == {"ar1", "mlr", "recommended"}
        rec = m["models"]["recommended"]  # compd fit --kind all's pick, what it stated and how that held
        assert "failed" in rec or (rec["stated"]["z"]["rms_um"] > 0 and rec["calibration"]["z"] > 0), rec
        for res in m["models"].values():
            # every model has figures or says why not: nothing is dropped
            assert "failed" in res or ("axes" in res and "reduction_pct" in res["axes"]["z"]), res
            if "axes" in res:
                assert "probed" in res and res["probed"]["every_h"] == 1.0
        assert m["logs_reused"] is False
    rows = {(r["model"], r["axis"]): r for r in doc["table"]}
    assert rows["ar1", "z"]["machines"] == 2 and "with_probes_median" in rows["ar1", "z"]
    assert (tmp_path / "w" / "lathe_1_machine.yaml").exists()
    assert h.machine_logs("lathe", 2, tmp_path / "w", False, 4.0)[3] is True  # the same machine: reused
    assert h.machine_logs("lathe", 2, tmp_path / "w", False, 3.0)[3] is False  # another day: logged again


def test_harness_counts_a_failed_fit():
    h = _harness()
    ok = {"axes": {"z": {"reduction_pct": 80.0}}}
    results = [
        {"kind": "lathe", "seed": s, "models": {"ar1": ok if s < 3 else {"failed": "fit: boom"}, "mlr": ok}}
        for s in (1, 2, 3)
    ]
    (row, _mlr) = h.summary_rows(results, ["lathe"])
    assert row["failed"] == 1 and row["worst"] == -math.inf and row["median"] == 80.0
    assert row["mlr_better_on"] == 1
    assert "fail" in h.table([row])


def test_harness_bad_arguments_exit_2(capsys):
    h = _harness()
    assert h.main(["--kinds", "mill"]) == 2
    assert h.main(["--seeds", "x"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 2


# --- compd testplan's plan as the training day -------------------------------------------
@pytest.mark.parametrize("kind", family.ALL_KINDS)
def test_the_plan_replaces_the_training_day_and_nothing_else(kind):
    for seed in (1, 2):
        day, plan = family.draw(kind, seed), family.draw(kind, seed, train="plan")
        assert plan.train.segments != day.train.segments
        # the same machine, unseen day and ambient: only the training duty differs
        assert plan.params == day.params and plan.unseen.to_dict() == day.unseen.to_dict()
        assert plan.train.ambient.to_dict() == day.train.ambient.to_dict() and plan.train.seed == day.train.seed
        assert {k: v for k, v in plan.drawn.items() if k != "plan"} == day.drawn
        assert plan.train.duration_s == 24 * 3600
        lo, hi = family.DUTY[kind]["limits"]
        level = "feed_mm_min" if kind in family.PLAN["axis"] else "speed_rpm"
        levels = sorted({getattr(s, level) for s in plan.train.segments} - {0.0})
        assert levels[0] == lo and levels[-1] == hi and len(levels) == (4 if level == "feed_mm_min" else 7)
        assert plan.train.segments[0].speed_rpm == plan.train.segments[0].feed_mm_min == 0.0  # idle first
        info = plan.drawn["plan"]
        assert info["probes"] == 145 and info["seed"] == seed and info["holds"] >= 8
        if level == "feed_mm_min":  # over the machine's whole travel
            travel = tuple(float(v) for v in day.params.get("stroke_mm", PLANTS.get(kind).DEFAULTS["stroke_mm"]))
            assert {s.stroke_mm for s in plan.train.segments if s.feed_mm_min > 0} == {travel}


def test_a_short_plan_day_scales_the_plan_and_keeps_a_round_trip_within_a_step():
    m = family.draw("gantry", 1, day_h=2.4, train="plan")
    info = m.drawn["plan"]
    assert m.train.duration_s == 2.4 * 3600 and info["probe_every_min"] == 1.0 and info["time_constant_min"] == 6.0
    stroke = m.train.segments[1].stroke_mm or (0.0, 1000.0)
    low = min(s.feed_mm_min for s in m.train.segments if s.feed_mm_min > 0)
    assert 2 * (stroke[1] - stroke[0]) / low * 60 <= 60.0  # one stroke out and back fits a 1 min step


def test_family_command_trains_on_the_plan(tmp_path, capsys):
    out = tmp_path / "f"
    assert (
        main(["family", "--kind", "spindle", "--seeds", "3", "--out", str(out), "--rate-s", "600", "--train", "plan"])
        == 0
    )
    doc = yaml.safe_load((out / "spindle_3_machine.yaml").read_text())
    assert doc["drawn"]["plan"]["levels"][-1] == 18000.0
    log = read_log(out / "spindle_3_train.csv")
    assert log.t_s[-1] == 86400.0 and set(log.col("speed_rpm")) >= set(doc["drawn"]["plan"]["levels"])
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["family", "--kind", "spindle", "--seeds", "3", "--out", str(out), "--train", "week"])
    assert e.value.code == 2 and "--train: invalid choice" in capsys.readouterr().err

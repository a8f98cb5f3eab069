"""`compd replay`: checked from the log, the staged run equal to the loop's own cycles, rates per simulated second."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.commissioning.replay import replay_model
from compd.log import read_log, write_log
from compd.plc.fanuc_pmc import FanucPmc
from hil_sim.plants.spindle import SpindlePlant
from hil_sim.scenario import Scenario

ALPHA, LENGTH_MM = 13.6e-6, 165.0


def spindle_log(path, hours: float = 3.0, seed: int = 3) -> None:
    """A 1 Hz log of the spindle plant: warm up, pause, warm again."""
    seg = hours * 3600.0 / 3
    sc = Scenario.from_dict(
        {
            "seed": seed,
            "segments": [
                {"duration_s": seg, "speed_rpm": 12000},
                {"duration_s": seg, "speed_rpm": 0},
                {"duration_s": seg, "speed_rpm": 8000},
            ],
        }
    )
    plant = SpindlePlant(sc)
    n = int(hours * 3600)
    rows = np.zeros((n, 1 + len(plant.signal_names)))
    for i in range(n):
        plant.advance_to(float(i))
        rows[i, 0] = i
        rows[i, 1:] = plant.sample()
    write_log(path, ["t_s", *plant.signal_names], rows)


@pytest.fixture(scope="module")
def log_and_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("replay")
    log = d / "spindle.csv"
    spindle_log(log)
    model = d / "xi.yaml"
    model.write_text(
        yaml.safe_dump(
            {
                "kind": "xi_spindle",
                "inputs": ["T_xi"],
                "outputs": ["z"],
                "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM, "t0_c": None},
                "fit": {},
            }
        )
    )
    return log, model


def test_report_matches_independent_computation(log_and_model):
    log_path, model_path = log_and_model
    result = replay_model(model_path, log_path)
    rep = result.report
    log = read_log(log_path)
    err = log.col("err_z_um")
    t_xi = log.col("T_xi")
    assert rep["rows"] == len(log)

    # before: straight from the log
    rms_before = float(np.sqrt(np.mean(err**2)))
    assert rep["axes"]["z"]["rms_before_um"] == pytest.approx(rms_before, rel=1e-12)

    # the correction the PLC should end up applying, computed from the log alone:
    # −α L (T_xi − T_xi[0]) rounded to 1 µm, subject to the 1 µm dead-band and the
    # guard's 5 µm/s slew. Where the slew does not bind, the PLC's shift is within
    # dead-band + ½ LSB of it.
    want = -ALPHA * LENGTH_MM * 1000.0 * (t_xi - t_xi[0])
    applied = result.applied_um[:, 0]
    settled = np.arange(len(log)) > 60
    assert np.max(np.abs(applied[settled] - want[settled])) <= 1.5 + 1e-9
    assert np.all(applied == np.round(applied))  # the PMC's shift is in whole µm

    # after: error + what the PLC applied, recomputed independently of the report
    resid = err + applied
    assert rep["axes"]["z"]["rms_after_um"] == pytest.approx(float(np.sqrt(np.mean(resid**2))), rel=1e-12)
    assert rep["axes"]["z"]["max_abs_after_um"] == pytest.approx(float(np.max(np.abs(resid))))
    # and bounded by the ideal compensation from the log
    ideal = float(np.sqrt(np.mean((err + want) ** 2)))
    assert abs(rep["axes"]["z"]["rms_after_um"] - ideal) < 1.0
    assert rep["axes"]["z"]["reduction_pct"] == pytest.approx(100 * (1 - rep["axes"]["z"]["rms_after_um"] / rms_before))
    assert rep["axes"]["z"]["reduction_pct"] > 50
    # every change of the word is one code; each is at most a few µm on a 1 Hz log
    n_changes = int(np.count_nonzero(np.diff(np.concatenate([[0], result.word]))))
    assert rep["codes_sent"] == n_changes > 10
    assert rep["saturated"] == 0
    assert "plc_alarm" not in rep["faults"]


def test_cli_replay_writes_report_and_plot(log_and_model, tmp_path, capsys):
    log_path, model_path = log_and_model
    report, plot = tmp_path / "r.json", tmp_path / "r.png"
    rc = main(
        ["replay", "--model", str(model_path), "--log", str(log_path), "--report", str(report), "--plot", str(plot)]
    )
    assert rc == 0
    rep = json.loads(report.read_text())
    assert set(rep) >= {"rows", "codes_sent", "axes", "saturated", "faults"}
    assert set(rep["axes"]["z"]) >= {"rms_before_um", "rms_after_um", "max_abs_after_um", "reduction_pct"}
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "rows" in capsys.readouterr().out


def test_cli_replay_needs_config_or_model(log_and_model, capsys):
    log_path, _ = log_and_model
    assert main(["replay", "--log", str(log_path)]) == 2
    assert "CONFIG" in capsys.readouterr().err


def test_replay_bad_log_is_exit_2(tmp_path, log_and_model, capsys):
    _, model_path = log_and_model
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,T_xi,err_z_um\n0,20,0\n1,abc,0\n")
    assert main(["replay", "--model", str(model_path), "--log", str(bad)]) == 2
    assert "T_xi" in capsys.readouterr().err


def test_replay_missing_input_column_is_exit_2(tmp_path, log_and_model, capsys):
    _, model_path = log_and_model
    bad = tmp_path / "nocol.csv"
    bad.write_text("t_s,T_other,err_z_um\n0,20,0\n1,20,0\n")
    assert main(["replay", "--model", str(model_path), "--log", str(bad)]) == 2
    assert "T_xi" in capsys.readouterr().err


def test_config_replay_against_pmc_over_modbus(tmp_path):
    """A config whose fanuc_pmc sink names an address: the replay drives a PMC scanning
    on its own over Modbus TCP, and agrees with the in-process PMC."""
    from compd.commissioning.replay import replay_config
    from compd.plc.fanuc_pmc import FanucPmc
    from hil_sim.devices.modbus_server import ModbusServerThread
    from hil_sim.devices.scan import PmcScanThread

    log = tmp_path / "short.csv"
    spindle_log(log, hours=0.75)
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            doc = {
                "sources": [
                    {"kind": "sim", "name": "unused", "plant": "spindle", "scenario": {"segments": [{"duration_s": 1}]}}
                ],
                "model": {
                    "kind": "xi_spindle",
                    "inputs": ["T_xi"],
                    "outputs": ["z"],
                    "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM},
                },
                "sink": {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": srv.port, "max_step_um": 5},
            }
            cfg = tmp_path / "c.yaml"
            cfg.write_text(yaml.safe_dump(doc))
            remote = replay_config(cfg, log)
    finally:
        scan.stop()
    doc["sink"] = {"kind": "fanuc_pmc", "max_step_um": 5}
    local_cfg = tmp_path / "local.yaml"
    local_cfg.write_text(yaml.safe_dump(doc))
    local = replay_config(local_cfg, log)
    assert remote.report["plc"].startswith("127.0.0.1:") and local.report["plc"] == "in_process"
    assert remote.report["codes_sent"] == local.report["codes_sent"] > 5
    np.testing.assert_array_equal(remote.applied_um, local.applied_um)
    assert pmc.alarms() == 0


def test_replay_applies_a_logs_probes_and_reports_without_them(log_and_model, tmp_path):
    """A model 20 % short of the truth, probed every 20 min: the adapted replay leaves less
    error than the model alone, which the report also gives; a +30 µm outlier is rejected."""
    log_path, model = log_and_model
    log = read_log(log_path)
    short = tmp_path / "short.yaml"
    doc = yaml.safe_load(model.read_text())
    doc["params"]["length_mm"] = LENGTH_MM * 0.8
    short.write_text(yaml.safe_dump(doc))
    e = log.col("err_z_um")
    probe = np.full(len(log), np.nan)
    rng = np.random.default_rng(4)
    for i in range(1200, len(log), 1200):
        probe[i] = e[i] + rng.normal(0.0, 0.3)
    probe[5400] = e[5400] + 30.0
    probed = tmp_path / "probed.csv"
    write_log(probed, log.columns + ["probe_z_um"], np.column_stack([log.data, probe]))
    plain = replay_model(short, log_path).report
    rep = replay_model(short, probed).report
    z = rep["axes"]["z"]
    assert "without_adaptation" not in plain["axes"]["z"] and "adaptation" not in plain
    assert z["without_adaptation"]["rms_after_um"] == pytest.approx(plain["axes"]["z"]["rms_after_um"])
    assert z["rms_after_um"] < 0.8 * z["without_adaptation"]["rms_after_um"], z
    ad = rep["adaptation"]
    print(z, ad)
    assert ad["probes"] == {"z": 9} and ad["rejected"] >= 1 and ad["accepted"] >= 6


def _big_error_log(path, n: int = 600) -> None:
    """A 1 Hz log whose ξ temperature rises so the spindle grows past 63 µm (about 80 µm)."""
    t = np.arange(n, dtype=float)
    temp = 20.0 + 36.0 * t / t[-1]  # 13.6e-6 × 165 mm × 36 K ≈ 80.8 µm at the end
    err = ALPHA * LENGTH_MM * 1000.0 * (temp - 20.0)
    write_log(path, ["t_s", "T_xi", "err_z_um"], np.column_stack([t, temp, err]))


def test_config_replay_drives_the_siemens_nc_with_its_resolution_and_no_word_clamp(tmp_path):
    """configs/modbus_rtu_siemens.yaml's sink (an NC gateway at an address) replays through the
    software PLC's Siemens NC in process: K0 moves in fine steps, not the word's 1 µm LSB, and
    past the word's ±63 µm when the guard allows it; the report names the NC."""
    from compd.commissioning.replay import replay_config

    src = yaml.safe_load(Path("configs/modbus_rtu_siemens.yaml").read_text(encoding="utf-8"))
    src["guard"]["max_abs_um"] = 200.0
    src["guard"]["max_slew_um_per_s"] = 4.0
    src["model"]["params"]["t0_c"] = 20.0
    cfg = tmp_path / "siemens.yaml"
    cfg.write_text(yaml.safe_dump(src))
    log = tmp_path / "big.csv"
    _big_error_log(log)
    res = replay_config(cfg, log)
    rep = res.report
    assert rep["device"] == "siemens_nc in process"
    assert rep["device_limits"]["resolution_um"] == pytest.approx(0.1)
    assert rep["device_limits"]["max_abs_um"] is None
    applied = res.applied_um[:, 0]
    assert applied.min() < -70.0  # past the word's 63 LSB: the NC has no such clamp
    frac = np.abs(applied - np.round(applied))
    assert (frac > 0.05).sum() > len(applied) // 4  # not whole-µm steps
    assert rep["axes"]["z"]["max_abs_after_um"] < 1.0
    # the same config replays unchanged from the file as shipped (the guard's ±63 µm clamp)
    shipped = replay_config("configs/modbus_rtu_siemens.yaml", log).report
    assert shipped["device"] == "siemens_nc in process"


def test_model_replay_says_it_uses_the_default_pmc(log_and_model, capsys):
    log, model = log_and_model
    rep = replay_model(model, log).report
    assert rep["device"].startswith("fanuc_pmc in process") and "default" in rep["device"]
    assert rep["device_limits"] == {"resolution_um": 1.0, "max_abs_um": 63.0, "max_rate_um_per_s": 250.0}


def test_config_replay_of_a_pci1756_over_modbus_uses_the_card_in_process(tmp_path):
    from compd.commissioning.replay import replay_config

    doc = {
        "sources": [{"kind": "replay", "name": "log", "path": "big.csv"}],
        "model": {
            "kind": "xi_spindle",
            "inputs": ["T_xi"],
            "outputs": ["z"],
            "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM, "t0_c": 20.0},
        },
        "codec": {"lsb_um": 0.5, "deadband_um": 0.5},
        "sink": {"kind": "pci1756", "device": "modbus", "host": "127.0.0.1", "port": 1},
    }
    cfg = tmp_path / "card.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    _big_error_log(tmp_path / "big.csv")
    res = replay_config(cfg, tmp_path / "big.csv")
    assert res.report["device"] == "pci1756 card in process"
    assert res.report["device_limits"]["max_abs_um"] == pytest.approx(31.5)
    assert res.applied_um[:, 0].min() == pytest.approx(-31.5)  # the word's full scale at 0.5 µm LSB


def test_config_replay_against_a_pmc_that_does_not_answer_is_one_line_exit_2(log_and_model, capsys):
    """configs/modbus_tcp_fanuc.yaml names a PMC at 127.0.0.1:5021: with nothing there the
    replay stops at once naming sink.host, instead of waiting on every row."""
    import socket

    text = Path("configs/modbus_tcp_fanuc.yaml").read_text(encoding="utf-8")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = Path(log_and_model[0]).parent / "fanuc_absent.yaml"
    cfg.write_text(text.replace("port: 5021", f"port: {port}"), encoding="utf-8")
    assert main(["replay", str(cfg), "--log", str(log_and_model[0])]) == 2
    err = capsys.readouterr().err.strip()
    assert f"{cfg}:" in err and "sink.host: the PMC at 127.0.0.1" in err and len(err.splitlines()) == 1


# ------------------------------------------- the staged replay gives the loop's own result

HOURS = 3.0
FEED_FIELD = {
    "kind": "feed_axis",
    "outputs": ["y"],
    "inputs": [
        "pos_y_mm",
        "T_base_000",
        "T_base_150",
        "T_base_300",
        "T_base_450",
        "T_base_600",
        "T_amb",
        "T_motor",
        "T_table",
        "T_head",
        "T_block",
    ],
    "params": {
        "length_mm": 600.0,
        "input_roles": [
            "position",
            "slide",
            "slide",
            "slide",
            "slide",
            "slide",
            "ambient",
            "offset",
            "offset",
            "offset",
            "offset",
        ],
        "field": {
            "slide_mm": [0.0, 150.0, 300.0, 450.0, 600.0],
            "gain_integral": 0.41,
            "gain_restraint": -0.342,
            "gain_ambient": -0.131,
            "offset_um_per_k": [0.037, 0.62, 0.566, -0.249],
        },
    },
}
FEED_ANALYTIC = {
    "kind": "feed_axis",
    "inputs": ["pos_y_mm", "current_y_a"],
    "outputs": ["y"],
    "params": {
        "length_mm": 600.0,
        "chi_per_m": 131.4,
        "eta": 90.59,
        "u1_k": 24.97,
        "u2_k": 0.0,
        "r_cu_ohm": 1.0,
        "input_roles": ["position", "current"],
    },
}
INLINE = {
    "ar1": {
        "kind": "ar1",
        "inputs": ["speed_rpm", "T3"],
        "outputs": ["z"],
        "params": {
            "dt_s": 60.0,
            "c1": 0.99363,
            "c2_table": [[2000.0, 0.3367]],
            "c1_table": [[2000.0, 0.98965]],
            "bed_gain_um_per_k": [6.265],
            "spindle_sign": -1,
            "recursion_start": "zero",
        },
    },
    "xi_spindle": {
        "kind": "xi_spindle",
        "inputs": ["T_xi", "speed_rpm"],
        "outputs": ["z"],
        "params": {
            "alpha_per_k": 1.36e-5,
            "length_mm": 164.7,
            "lift": {"k_um_per_rpm2": 2.61e-8, "speed_input": "speed_rpm", "preload_share": 0.8},
        },
    },
    "feed_field": FEED_FIELD,
    "feed_analytic": FEED_ANALYTIC,
    "feed_linear": {**FEED_ANALYTIC, "params": {**FEED_ANALYTIC["params"], "linear_p0_mm": 300.0}},
    # the ξ sensor's lag led (compd.models.lead): the batch leads the inputs as the cycle does
    "xi_lead": {
        "kind": "xi_spindle",
        "inputs": ["T_xi", "speed_rpm"],
        "outputs": ["z"],
        "params": {
            "alpha_per_k": 1.36e-5,
            "length_mm": 164.7,
            "lead_s": [180.0, 0.0],
            "lead_filter_s": [36.0, 0.0],
            "lift": {"k_um_per_rpm2": 2.61e-8, "speed_input": "speed_rpm", "preload_share": 0.8},
        },
    },
}
MACHINE = {
    "ar1": "lathe",
    "xi_spindle": "spindle",
    "xi_lead": "spindle",
    "lvr": "gantry",
    "mlr": "gantry",
    "feed_field": "feed_axis",
    "feed_analytic": "feed_axis",
    "feed_linear": "feed_axis",
}


@pytest.fixture(scope="module")
def machines(tmp_path_factory):
    """The first hours of each hil_sim machine's unseen day at 1 s, and a file per model
    (inline params, or an lvr and an mlr fitted on the gantry's training day at 60 s)."""
    from hil_sim.logcmd import load_plant, run_log

    d = tmp_path_factory.mktemp("machines")
    logs = {}
    for m in ("lathe", "spindle", "gantry", "feed_axis"):
        run_log(load_plant(f"hil_sim/scenarios/{m}_unseen.yaml"), d / f"{m}.csv", 1.0, HOURS * 3600)
        logs[m] = read_log(d / f"{m}.csv", allow_nan=True)
    run_log(load_plant("hil_sim/scenarios/gantry_train.yaml"), d / "gantry_train.csv", 60.0, 12 * 3600)
    for kind in ("lvr", "mlr"):
        assert (
            main(["fit", "--kind", kind, "--log", str(d / "gantry_train.csv"), "--out", str(d / f"{kind}.yaml")]) == 0
        )
    for name, doc in INLINE.items():
        (d / f"{name}.yaml").write_text(yaml.safe_dump(doc))
    return d, logs


def _model(d, name):
    from compd.commissioning.fitting import load_model

    return load_model(d / f"{name}.yaml")


def _sink(kind, **kw):
    from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink
    from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink
    from compd.sinks.siemens import SiemensConfig, SiemensSink

    if kind == "pci1756":
        return Pci1756Sink(Pci1756Config(kind="pci1756", **kw))
    if kind == "siemens":
        return SiemensSink(SiemensConfig(kind="siemens", **kw))
    if kind == "fanuc_shift":
        return FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode="shift", **kw))
    return FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", **kw))


def _both(log, make_model, sink_kind, **kw):
    """The replay cycle by cycle (the loop's own `step`) and staged: every trace and the report equal
    (the prediction and correction to 1e-9 µm: a linear model's batch matrix product rounds in
    another order than its row by row dot product)."""
    from compd.commissioning.replay import replay_log

    ref = replay_log(log, make_model(), _sink(sink_kind), per_row=True, **kw)
    got = replay_log(log, make_model(), _sink(sink_kind), **kw)
    assert got.report == ref.report
    np.testing.assert_array_equal(got.applied_um, ref.applied_um)
    np.testing.assert_array_equal(got.word, ref.word)
    for key in ("guard_state", "enable", "commanded_um"):
        np.testing.assert_array_equal(got.extra[key], ref.extra[key], err_msg=key)
    for key in ("pred_um", "corr_um"):
        np.testing.assert_allclose(got.extra[key], ref.extra[key], rtol=0, atol=1e-9, err_msg=key)
    return ref, got


def _stepped(model, X, t):
    """The model as the loop steps it: started on the first row, run when due (update_period_s)."""
    out = np.zeros((len(t), len(model.outputs)))
    row = np.zeros(len(model.outputs))
    due = -np.inf
    model.start(X[0], float(t[0]))
    for i in range(len(t)):
        if t[i] >= due:
            model.run(X[i], float(t[i]), row)
            due = t[i] + model.update_period_s if model.update_period_s > 0 else -np.inf
        out[i] = row
    return out


def test_predict_equals_stepping_for_every_kind_the_replay_batches(machines):
    """compd.commissioning.replay.BATCH_MODELS: each class's `predict` over a day equals the loop stepping it,
    and leaves the model where stepping does (the rows after continue alike)."""
    from compd.commissioning.replay import BATCH_MODELS

    d, logs = machines
    seen = set()
    for name in ("ar1", "xi_spindle", "xi_lead", "lvr", "mlr", "feed_field", "feed_analytic"):
        log = logs[MACHINE[name]]
        batch, step = _model(d, name), _model(d, name)
        X, t = log.matrix(batch.inputs), log.t_s
        cut = len(t) - 50
        np.testing.assert_allclose(
            batch.predict(X[:cut], t[:cut]), _stepped(step, X[:cut], t[:cut]), rtol=0, atol=1e-9, err_msg=name
        )
        a, b = np.zeros(len(batch.outputs)), np.zeros(len(batch.outputs))
        for i in range(cut, len(t), 10):  # on from the state each left
            batch.run(X[i], float(t[i]), a)
            step.run(X[i], float(t[i]), b)
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9, err_msg=name)
        seen.add(f"{type(batch).__module__}.{type(batch).__qualname__}")
    assert seen == BATCH_MODELS


@pytest.mark.parametrize(
    ("name", "sink"),
    [
        ("ar1", "fanuc"),
        ("xi_spindle", "fanuc_shift"),
        ("xi_lead", "fanuc"),
        ("lvr", "pci1756"),
        ("mlr", "siemens"),
        ("feed_field", "pci1756"),
        ("feed_analytic", "fanuc"),
        ("feed_linear", "siemens"),
    ],
)
def test_staged_replay_equals_the_loops_cycles_for_every_kind(machines, name, sink):
    """Every model kind (feed_axis with linear_p0_mm: the Siemens sink sends each row's tanβ)."""
    d, logs = machines
    ref, got = _both(logs[MACHINE[name]], lambda: _model(d, name), sink)
    assert ref.report["codes_sent"] > 0
    if name == "feed_linear":  # the NC got the model's slope, not the position-independent form alone
        assert got.report["device"] == "siemens_nc in process"


def _bad_inputs(log, rows):
    """The gantry log's first `rows`, with bad inputs: a sensor without data for a stretch
    (lvr predicts degraded), one out of range, one jumping faster than its rate limit, an
    infinite reading, a time stamp repeated."""
    from compd.log import Log

    data = log.data[:rows].copy()
    col = {c: k for k, c in enumerate(log.columns)}
    data[1000:1100, col["T10"]] = np.nan
    data[2000:2006, col["T11"]] = 95.0
    data[3000, col["T12"]] += 5.0
    data[3500, col["T13"]] = np.inf
    data[4001, 0] = data[4000, 0]
    return Log(log.file, list(log.columns), data)


BAD_GUARD = {
    "fault_policy": "ramp_to_zero",
    "recovery_s": 30.0,
    "signals": {"T11": {"min": 0.0, "max": 80.0}, "T12": {"max_rate_per_s": 0.5}},
}


@pytest.mark.parametrize("sink", ["pci1756", "fanuc", "fanuc_shift", "siemens"])
def test_staged_replay_equals_the_loops_cycles_with_bad_inputs(machines, sink):
    """Stale/range/rate faults, a degraded stretch and their recovery, through every sink: the
    rows where the guard's checks matter run them (and the model row by row after the first)."""
    from compd.core.config import GuardConfig

    d, logs = machines
    log = _bad_inputs(logs["gantry"], 5400)
    ref, _ = _both(log, lambda: _model(d, "lvr"), sink, guard_cfg=GuardConfig(**BAD_GUARD))
    faults = ref.report["faults"]
    assert {"bad:no_data", "bad:out_of_range", "bad:implausible"} <= set(faults), faults
    assert faults.get("model:degraded") or any(k.startswith("degraded") for k in faults), faults


def test_staged_replay_equals_the_loops_cycles_when_the_first_row_is_bad(machines):
    """A bad first row: no batch at all, the model started on the first good row."""
    from compd.core.config import GuardConfig
    from compd.log import Log

    d, logs = machines
    log = logs["gantry"]
    data = log.data[:1500].copy()
    data[:3, log.columns.index("T0")] = np.nan
    _both(Log(log.file, list(log.columns), data), lambda: _model(d, "mlr"), "fanuc", guard_cfg=GuardConfig(**BAD_GUARD))


def test_staged_replay_equals_the_loops_cycles_with_frozen_limits(machines):
    """A frozen-input limit looks further back than one row: every row is checked for real."""
    from compd.core.config import GuardConfig
    from compd.log import Log

    d, logs = machines
    log = logs["lathe"]
    data = log.data.copy()
    data[2000:6000, log.columns.index("T3")] = data[2000, log.columns.index("T3")]  # stuck while the spindle starts
    guard = GuardConfig(signals={"T3": {"frozen_after_s": 600.0, "frozen_band": 0.05}})
    ref, _ = _both(Log(log.file, list(log.columns), data), lambda: _model(d, "ar1"), "fanuc", guard_cfg=guard)
    assert "bad:frozen" in ref.report["faults"]


def test_staged_replay_equals_the_loops_cycles_with_probes(machines, tmp_path):
    """The probe adapter between model and guard, and the replay without it for the report."""
    from compd.commissioning.fitting import load_model
    from compd.log import Log

    d, logs = machines
    log = logs["spindle"]
    doc = dict(INLINE["xi_spindle"], params={**INLINE["xi_spindle"]["params"], "length_mm": 0.8 * 164.7})
    (tmp_path / "short.yaml").write_text(yaml.safe_dump(doc))
    probe = np.full(len(log), np.nan)
    probe[600::900] = log.col("err_z_um")[600::900] + 0.2
    probe[4200] += 30.0  # an outlier, rejected
    probed = Log(log.file, log.columns + ["probe_z_um"], np.column_stack([log.data, probe]))
    ref, _ = _both(probed, lambda: load_model(tmp_path / "short.yaml"), "fanuc")
    assert ref.report["adaptation"]["accepted"] >= 5 and ref.report["adaptation"]["rejected"] >= 1
    assert "without_adaptation" in ref.report["axes"]["z"]


def test_staged_replay_equals_the_loops_cycles_with_inhibit(machines):
    """The log's inhibit and referenced columns hold the axis off and release it."""
    from compd.core.config import InhibitConfig
    from compd.log import Log

    d, logs = machines
    log = logs["lathe"]
    n = len(log)
    inhibit = np.zeros(n)
    inhibit[3000:3400] = 1.0
    inhibit[7000:7010] = np.nan  # the signal lost: inhibits
    referenced = np.ones(n)
    referenced[:200] = 0.0
    held = Log(log.file, log.columns + ["inhibit", "ref_z"], np.column_stack([log.data, inhibit, referenced]))
    cfg = InhibitConfig(signal="inhibit", axes={"z": {"referenced": "ref_z"}})
    ref, _ = _both(held, lambda: _model(d, "ar1"), "fanuc", inhibit_cfg=cfg)
    assert ref.report["faults"].get("held:inhibited") and ref.report["faults"].get("held:waiting for reference")


# -------------------------------------------- rates per simulated second, not per row


def _ramps_log(path, step_s: float) -> None:
    """An error of ramps at 1 µm/s (faster than a PMC step per 10 s row, slower than the guard's
    5 µm/s and the NC's ramp) and slow drifts, logged every `step_s`: T_xi, err_z_um."""
    t = np.arange(0.0, 7200.0 + 1e-9, step_s)
    err = np.interp(t, [0, 300, 340, 1500, 1560, 3000, 3050, 5000, 7200], [0, 0, 40, 43, 13, 12, 57, 50, 20])
    temp = 20.0 + err / (ALPHA * LENGTH_MM * 1000.0)
    write_log(path, ["t_s", "T_xi", "err_z_um"], np.column_stack([t, temp, err]))


XI_CONFIG = {
    "sources": [{"kind": "replay", "name": "log", "path": "ramps.csv"}],
    "model": {
        "kind": "xi_spindle",
        "inputs": ["T_xi"],
        "outputs": ["z"],
        "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM, "t0_c": 20.0},
    },
}


@pytest.mark.parametrize(
    "sink",
    [
        {"kind": "fanuc_pmc"},
        {"kind": "fanuc_pmc", "mode": "shift"},
        {"kind": "pci1756"},
        {"kind": "siemens"},
    ],
)
def test_rows_1_s_or_10_s_apart_give_the_same_applied_correction(tmp_path, sink):
    """The same model and error logged every second and every 10 s: at the times both have,
    the guard's correction is the same (its slew does not bind) and so is what the device
    applied, to the device's resolution — the FANUC sink moves its shift as far in a 10 s
    row as in ten 1 s rows, the NC ramps over the row's time."""
    from compd.commissioning.replay import replay_config

    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({**XI_CONFIG, "sink": sink}))
    _ramps_log(tmp_path / "ramps.csv", 1.0)
    _ramps_log(tmp_path / "ramps10.csv", 10.0)
    one = replay_config(cfg, tmp_path / "ramps.csv")
    ten = replay_config(cfg, tmp_path / "ramps10.csv")
    np.testing.assert_allclose(ten.extra["corr_um"], one.extra["corr_um"][::10], rtol=0, atol=1e-9)
    res = one.report["device_limits"]["resolution_um"]
    diff = np.abs(ten.applied_um[:, 0] - one.applied_um[::10, 0])
    # the word's dead-band band: each replay's word within one LSB of the same correction
    assert diff.max() <= res + 1e-6, (diff.max(), np.flatnonzero(diff > res + 1e-6)[:5])
    assert one.report["axes"]["z"]["max_abs_after_um"] < 2.5
    for r in (one, ten):
        assert "plc_alarm" not in r.report["faults"]
        assert abs(r.report["axes"]["z"]["reduction_pct"] - one.report["axes"]["z"]["reduction_pct"]) < 1.0


class SpyPmc(FanucPmc):
    """A FANUC PMC that records every change of its applied shift: (scan count, axis, change µm)."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.changes: list[tuple[int, int, float]] = []

    def scan(self) -> bool:
        before = self.applied_um()
        changed = super().scan()
        for a, (b, c) in enumerate(zip(before, self.applied_um(), strict=True)):
            if c != b:
                self.changes.append((self.scans, a, c - b))
        return changed


def test_fanuc_replay_of_10_s_rows_is_not_limited_to_one_step_per_row(tmp_path):
    """10 s rows through the FANUC PMC: a row moves the shift by up to 10 µm (1 µm/s), in
    steps of at most max_step_um, each two PMC scans or more after the one before, never an
    alarm; the machine applies at every row what the word commands, as the PCI-1756 card
    does, so both score the same."""
    from compd.commissioning.fitting import load_model
    from compd.commissioning.replay import replay_log
    from compd.core.config import CodecConfig, GuardConfig
    from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink
    from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink

    _ramps_log(tmp_path / "ramps10.csv", 10.0)
    log = read_log(tmp_path / "ramps10.csv")
    doc = yaml.safe_load(yaml.safe_dump(XI_CONFIG["model"]))
    (tmp_path / "xi.yaml").write_text(yaml.safe_dump({**doc, "fit": {}}))
    pmc = SpyPmc(step_limit_um=10)
    fanuc = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", max_step_um=5, min_update_s=0.02), pmc=pmc)
    res = replay_log(log, load_model(tmp_path / "xi.yaml"), fanuc, GuardConfig(), CodecConfig())
    card = replay_log(
        log, load_model(tmp_path / "xi.yaml"), Pci1756Sink(Pci1756Config(kind="pci1756")), GuardConfig(), CodecConfig()
    )
    applied = res.applied_um[:, 0]
    np.testing.assert_array_equal(applied, res.extra["commanded_um"][:, 0])  # no trailing at any row
    np.testing.assert_array_equal(applied, card.applied_um[:, 0])
    assert res.report["axes"] == card.report["axes"]
    assert np.abs(np.diff(applied)).max() >= 9.0  # 1 µm/s × 10 s in one row, not 5 µm (max_step_um)
    steps = np.array([c[2] for c in pmc.changes])
    scans = np.array([c[0] for c in pmc.changes if c[1] == 0])
    assert np.abs(steps).max() <= 5.0
    assert np.diff(scans).min() >= 2  # the PMC scanned at least twice between two steps
    assert pmc.alarms() == 0 and "plc_alarm" not in res.report["faults"]


@pytest.mark.parametrize("spacing", ["1 s", "10 s", "irregular"])
def test_the_guards_slew_holds_per_second_of_simulated_time(tmp_path, spacing):
    """A 40 µm step in the error: the guard's correction, and what the PMC applies, move at
    most max_slew_um_per_s × the time between rows (the applied within the word's LSB)."""
    from compd.commissioning.replay import replay_config

    rng = np.random.default_rng(5)
    if spacing == "irregular":
        t = np.cumsum(rng.uniform(0.3, 25.0, 600))
    else:
        t = np.arange(0.0, 3000.0, 1.0 if spacing == "1 s" else 10.0)
    err = np.where(t > 0.3 * t[-1], 40.0, 0.0) + np.where(t > 0.7 * t[-1], -25.0, 0.0)
    temp = 20.0 + err / (ALPHA * LENGTH_MM * 1000.0)
    write_log(tmp_path / "ramps.csv", ["t_s", "T_xi", "err_z_um"], np.column_stack([t, temp, err]))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({**XI_CONFIG, "guard": {"max_slew_um_per_s": 2.0}, "sink": {"kind": "fanuc_pmc"}}))
    res = replay_config(cfg, tmp_path / "ramps.csv")
    dt = np.diff(t)
    corr = res.extra["corr_um"][:, 0]
    assert np.all(np.abs(np.diff(corr)) <= 2.0 * dt + 1e-9)
    assert np.all(np.abs(np.diff(res.applied_um[:, 0])) <= 2.0 * dt + 1.0 + 1e-9)
    assert np.abs(corr).max() > 39.0  # it got there


def test_the_siemens_nc_applies_its_slope_where_the_log_says_the_axis_stood(machines):
    """A position-dependent model through the Siemens sink: the NC in process is told each row's
    pos_<axis>_mm, as the machine's NC knows its axis, so ΔK = K0 + tanβ·(P − P0) is taken there
    (before, P stayed 0 in a replay)."""
    from compd.commissioning.replay import replay_log
    from compd.log import Log

    d, logs = machines
    log = logs["feed_axis"]
    moving = replay_log(log, _model(d, "feed_linear"), _sink("siemens"))
    data = log.data.copy()
    data[:, log.columns.index("pos_y_mm")] = 300.0  # the axis parked at P0: ΔK is K0 alone
    parked = replay_log(Log(log.file, list(log.columns), data), _model(d, "feed_linear"), _sink("siemens"))
    np.testing.assert_allclose(parked.extra["pred_um"], moving.extra["pred_um"])  # K0 does not move with P
    k0 = parked.extra["commanded_um"][:, 0]
    ok = np.isfinite(k0)
    # the NC targets the K0 last sent (the sink sends a change of min_change_um, 0.1 µm)
    np.testing.assert_allclose(k0[ok], parked.extra["corr_um"][ok, 0], atol=0.15)
    slope_part = (moving.extra["commanded_um"][:, 0] - k0)[ok]
    far = np.abs(log.col("pos_y_mm")[ok] - 300.0) > 200.0
    assert np.percentile(np.abs(slope_part[far]), 90) > 0.2  # the slope's share, where the axis is far from P0

"""`compd replay` of a hil_sim spindle log through the PMC software PLC, checked from the log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.log import read_log, write_log
from compd.replay import replay_model
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
    assert rep["axes"]["z"]["reduction_pct"] == pytest.approx(
        100 * (1 - rep["axes"]["z"]["rms_after_um"] / rms_before)
    )
    assert rep["axes"]["z"]["reduction_pct"] > 50
    # every change of the word is one code; each is at most a few µm on a 1 Hz log
    n_changes = int(np.count_nonzero(np.diff(np.concatenate([[0], result.word]))))
    assert rep["codes_sent"] == n_changes > 10
    assert rep["saturated"] == 0
    assert "plc_alarm" not in rep["faults"]


def test_cli_replay_writes_report_and_plot(log_and_model, tmp_path, capsys):
    log_path, model_path = log_and_model
    report, plot = tmp_path / "r.json", tmp_path / "r.png"
    rc = main(["replay", "--model", str(model_path), "--log", str(log_path), "--report", str(report), "--plot", str(plot)])
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
    from compd.plc.fanuc_pmc import FanucPmc
    from compd.replay import replay_config
    from hil_sim.devices.modbus_server import ModbusServerThread
    from hil_sim.devices.scan import PmcScanThread

    log = tmp_path / "short.csv"
    spindle_log(log, hours=0.75)
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            doc = {
                "sources": [{"kind": "sim", "name": "unused", "plant": "spindle", "scenario": {"segments": [{"duration_s": 1}]}}],
                "model": {"kind": "xi_spindle", "inputs": ["T_xi"], "outputs": ["z"],
                          "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM}},
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


@pytest.mark.bench
def test_bench_day_of_1hz_log(tmp_path, log_and_model):
    """86 400 rows (a day at 1 Hz) through the PMC: the target is seconds, not minutes."""
    import time

    _, model_path = log_and_model
    log = tmp_path / "day.csv"
    spindle_log(log, hours=24.0)
    t0 = time.perf_counter()
    result = replay_model(model_path, log)
    wall_s = time.perf_counter() - t0
    print(f"replay of {result.report['rows']} rows: {wall_s:.2f} s")
    assert result.report["rows"] == 86400
    assert wall_s < 60.0


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
    from compd.replay import replay_config

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
    from compd.replay import replay_config

    doc = {
        "sources": [{"kind": "replay", "name": "log", "path": "big.csv"}],
        "model": {"kind": "xi_spindle", "inputs": ["T_xi"], "outputs": ["z"],
                  "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM, "t0_c": 20.0}},
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

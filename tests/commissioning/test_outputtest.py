"""`compd output-test`: a known correction via the configured sink to a real device, read back, ramped at the slew."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.commissioning.outputtest import run_output_test
from compd.config import load_config
from compd.plc.fanuc_pmc import FanucPmc
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.scan import PmcScanThread


def _config(tmp_path, sink: dict, *, slew: float = 2.0, period_s: float = 0.002, codec: dict | None = None) -> str:
    doc = {
        "loop": {"period_s": period_s},
        "sources": [{"kind": "replay", "name": "log", "path": "unused.csv"}],
        "model": {
            "kind": "xi_spindle",
            "inputs": ["T_xi"],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0},
        },
        "guard": {"max_slew_um_per_s": slew, "max_abs_um": 40.0},
        "sink": sink,
    }
    if codec:
        doc["codec"] = codec
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def _assert_ramps_at_the_slew(res) -> None:
    c = np.asarray(res.correction_um)
    step = res.slew_um_per_s * res.period_s
    assert np.max(np.abs(np.diff(c))) <= step + 1e-9
    assert c.max() == pytest.approx(max(res.commanded_um, 0.0)) and c.min() == pytest.approx(min(res.commanded_um, 0.0))
    assert c[-1] == 0.0


def test_software_plc_pmc_in_process_applies_and_reads_back(tmp_path):
    cfg = load_config(_config(tmp_path, {"kind": "fanuc_pmc"}))
    res = run_output_test(cfg, "z", 5.0, hold_s=1.0, say=lambda _: None)
    assert res.device == "fanuc_pmc in process"
    assert res.applied_um == 5.0 and res.word == 0xC500
    assert res.applied_after_um == 0.0
    assert res.matches(res.resolution_um)
    _assert_ramps_at_the_slew(res)
    # 5 µm at 2 µm/s in 2 ms cycles: 1250 cycles up, as many down
    assert len(res.correction_um) > 2 * 1250


def test_fanuc_pmc_over_modbus_tcp_reads_back_what_the_pmc_applied(tmp_path):
    """The PMC scanning on its own thread, served over Modbus TCP on 127.0.0.1: the read-back is
    the PMC's applied shift; the ramp is one period's slew per cycle however late a cycle ran."""
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            path = _config(
                tmp_path, {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": srv.port}, slew=10.0, period_s=0.01
            )
            res = run_output_test(load_config(path), "z", -4.0, hold_s=0.3, say=lambda _: None)
            after = pmc.applied_um()
    finally:
        scan.stop()
    assert res.device == f"fanuc_pmc at 127.0.0.1:{srv.port}"
    assert res.applied_um == -4.0 and res.word == 0x4400  # enable, negative, 4 LSB
    assert res.applied_after_um == 0.0 and after == [0.0, 0.0]
    assert pmc.alarms() == 0
    _assert_ramps_at_the_slew(res)


def test_siemens_nc_applies_the_commanded_k0_finely(tmp_path):
    cfg = load_config(_config(tmp_path, {"kind": "siemens", "axes": {"z": 1}}, slew=4.0))
    res = run_output_test(cfg, "z", 7.3, hold_s=3.0, say=lambda _: None)
    assert res.device == "siemens_nc in process"
    # K0 is sent once it moved by min_change_um (0.1 µm): the NC holds the last one sent
    assert abs(res.applied_um - 7.3) <= 0.1 + 1e-6 and res.matches(res.resolution_um)
    assert abs(res.applied_um - round(res.applied_um)) > 0.05  # not a whole µm: no word here
    assert abs(res.applied_after_um) < 1e-6
    _assert_ramps_at_the_slew(res)
    dev = np.asarray(res.device_um)
    cap_um = 1e-5 * 30000 / 60 * 0.004 * 1000  # MD32760 × v_max × IPO: 0.02 µm per 4 ms IPO cycle
    assert np.max(np.abs(np.diff(dev))) <= cap_um + 1e-6  # the NC's own ramp, never a step


def test_pci1756_card_word_reads_back_at_the_codec_lsb(tmp_path):
    path = _config(tmp_path, {"kind": "pci1756"}, codec={"lsb_um": 0.5, "deadband_um": 0.5})
    res = run_output_test(load_config(path), "z", 2.5, hold_s=0.5, say=lambda _: None)
    assert res.device == "pci1756 card in process"
    assert res.applied_um == 2.5 and res.applied_after_um == 0.0
    _assert_ramps_at_the_slew(res)


def test_cli_output_test_with_yes_prints_commanded_and_applied(tmp_path, capsys):
    path = _config(tmp_path, {"kind": "fanuc_pmc"}, slew=20.0)
    out = tmp_path / "r.json"
    assert main(["output-test", path, "--axis", "z", "--um", "3", "--hold-s", "1", "--yes", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "commanded +3.000 um, applied +3.000 um: ok" in text
    rep = json.loads(out.read_text())
    assert rep["applied_um"] == 3.0 and rep["matches"] is True
    assert rep["max_step_um"] <= 20.0 * 0.002 + 1e-9
    # the contract's spelling: --config CONFIG
    assert main(["output-test", "--config", path, "--axis", "z", "--um", "-2", "--hold-s", "0.5", "--yes"]) == 0
    assert "commanded -2.000 um, applied -2.000 um: ok" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--axis", "x", "--um", "5", "--yes"], "--axis: 'x' is not an axis the sink drives (known: z)"),
        (["--axis", "z", "--um", "41", "--yes"], "--um: |41| um is beyond the guard's max correction"),
        (["--axis", "z", "--um", "0.5", "--yes"], "inside the codec's dead-band"),
        (["--axis", "z", "--um", "5"], "--yes: writes a correction to the machine"),  # stdin is no terminal here
    ],
)
def test_cli_output_test_bad_input_is_one_line_exit_2(tmp_path, capsys, argv, needle):
    path = _config(tmp_path, {"kind": "fanuc_pmc"})
    assert main(["output-test", path, *argv]) == 2
    err = capsys.readouterr().err
    assert needle in err and path in err and len(err.strip().splitlines()) == 1


def test_a_device_that_does_not_answer_gets_nothing_written(tmp_path, capsys, monkeypatch):
    import socket

    import compd.commissioning.outputtest

    monkeypatch.setattr(compd.commissioning.outputtest, "LINK_WAIT_S", 0.3)
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = _config(tmp_path, {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": port}, period_s=0.01)
    assert main(["output-test", path, "--axis", "z", "--um", "5", "--yes"]) == 1
    err = capsys.readouterr().err
    assert f"fanuc_pmc at 127.0.0.1:{port} does not answer" in err and "nothing written" in err


def test_refuses_beside_a_running_daemon_of_the_config(tmp_path, capsys):
    import os
    import time

    path = _config(tmp_path, {"kind": "fanuc_pmc"})
    from compd.cycle.statusblock import SCHEMA

    with open(path, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    doc["status"] = {"path": "status.json"}
    with open(path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh)
    status = {
        "schema": SCHEMA,
        "pid": os.getpid(),
        "state": "running",
        "written_unix_s": time.time(),
        "status_period_s": 1.0,
    }
    (tmp_path / "status.json").write_text(json.dumps(status))
    assert main(["output-test", path, "--axis", "z", "--um", "5", "--yes"]) == 1
    assert "a daemon of this config is running" in capsys.readouterr().err
    status["state"] = "stopped"
    (tmp_path / "status.json").write_text(json.dumps(status))
    assert main(["output-test", path, "--axis", "z", "--um", "5", "--hold-s", "0.1", "--yes"]) == 0


def test_an_interrupt_ramps_back_to_zero_at_the_slew(tmp_path):
    """Ctrl-C (or SIGTERM, which the CLI turns into it) after the ramp up: back to zero at the
    slew, then the safe state; the result says it was interrupted."""

    def say(text: str) -> None:
        if text.startswith("  ramped up"):
            raise KeyboardInterrupt

    cfg = load_config(_config(tmp_path, {"kind": "fanuc_pmc"}))
    res = run_output_test(cfg, "z", -6.0, hold_s=5.0, say=say)
    assert res.interrupted and res.applied_after_um == 0.0
    assert not res.matches(res.resolution_um)  # no read-back during a hold that never ran
    _assert_ramps_at_the_slew(res)

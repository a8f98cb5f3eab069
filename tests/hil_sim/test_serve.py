"""`python -m hil_sim serve`: devices from YAML, where they listen, clean stop on Ctrl-C."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import yaml
from pymodbus.client import ModbusTcpClient

from compd.sources.modbus import ModbusConfig, ModbusSource
from tests.conftest import ROOT
from tests.sources.helpers import Harness


def test_serve_prints_where_and_stops_on_sigint(tmp_path):
    cfg = {
        "devices": [
            {"kind": "pt100_modbus", "name": "tx", "port": 0, "channels": [{"name": "T1", "value_c": 24.6}]},
            {
                "kind": "pt100_modbus",
                "name": "rtu",
                "transport": "rtu",
                "serial_port": str(tmp_path / "dev"),
                "pty_link": str(tmp_path / "compd"),
                "channels": [{"name": "T2", "value_c": 21.5}],
            },
            {"kind": "fanuc_pmc", "name": "pmc", "port": 0},
            {"kind": "siemens_nc", "name": "nc", "port": 0},
            {
                "kind": "dcon",
                "name": "adam",
                "serial_port": str(tmp_path / "ddev"),
                "pty_link": str(tmp_path / "dcon"),
                "channels": [{"name": "T3"}],
            },
        ]
    }
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil_sim", "serve", "--config", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        lines = []
        while True:
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
            lines.append(line)
            if "ready" in line:
                break
        ports = {m[0]: int(m[1]) for m in re.findall(r"^(\w+): \w+ on tcp:127\.0\.0\.1:(\d+)", "".join(lines), re.M)}
        assert set(ports) == {"tx", "pmc", "nc"}
        c = ModbusTcpClient("127.0.0.1", port=ports["pmc"], timeout=1, retries=0)
        try:
            rr = c.read_holding_registers(400, count=2, device_id=1)
            assert not rr.isError() and rr.registers[0] + rr.registers[1] > 0  # the PMC scans
        finally:
            c.close()
        src = ModbusSource(
            ModbusConfig.model_validate(
                {
                    "kind": "modbus",
                    "name": "m",
                    "transport": "rtu",
                    "serial_port": str(tmp_path / "compd"),
                    "baudrate": 115200,
                    "timeout_s": 0.2,
                    "channels": [{"name": "T2", "address": 0}],
                }
            )
        )
        with Harness(src) as h:
            assert h.sample()["T2"][1] == "GOOD"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert "stopped" in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_bench_file_in_repo_loads():
    from hil_sim.serve import load

    kinds = {d["kind"] for d in load(ROOT / "hil_sim" / "benches" / "all_devices.yaml")}
    assert kinds == {"pt100_modbus", "dcon", "can_pt100", "fanuc_pmc", "siemens_nc"}

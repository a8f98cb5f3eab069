"""The closed loop on a real controller: LinuxCNC runs compd's thermal test, hil_sim's spindle turns at LinuxCNC's
spindle speed, compd compensates through LinuxCNC's external offsets, the error at the tool is the plant's growth
minus the offset LinuxCNC applied (read from HAL by the plant, not from compd).

The short run (make test): `compd testplan` designs an 8 h test, its LinuxCNC program runs with its dwells scaled
by the plant's speedup (480: a minute of wall time), and the test checks that the offset follows compd's status
within 1 µm while the program runs (the reads in which compd's correction held still: a read through halcmd takes
tens of ms, in which a slewing correction moves), that the error at the tool is cut, and that SIGTERM leaves 0. Every wait is a
condition with a generous deadline."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from hil_sim.devices.plant import residual_report
from rig.closedloop import ROOT, env, start_serve, stop_serve
from tests.linuxcnc.sim import Sim, require, wait_for

SPEEDUP = 480.0  # plant seconds per wall second: the 8 h test in a minute
HOURS = 8
MODEL = {  # the demo's ξ-point model of hil_sim's spindle (configs/demo.yaml)
    "kind": "xi_spindle", "inputs": ["T_xi", "speed_rpm"], "outputs": ["z"],
    "params": {"alpha_per_k": 13.6e-6, "length_mm": 164.71, "t0_c": None, "xi_mm": 55.2,
               "lift": {"k_um_per_rpm2": 2.611e-8, "speed_input": "speed_rpm"}},
}


def _scaled(program: str, speedup: float) -> str:
    """The program with every dwell divided by the plant's speedup (its thermal time runs that much faster)."""
    return re.sub(r"^G4 P([0-9.]+)$", lambda m: f"G4 P{float(m.group(1)) / speedup:.4f}", program, flags=re.M)


def test_linuxcnc_runs_compd_s_thermal_test_and_compd_compensates_the_plant_through_its_offsets(tmp_path: Path):
    _, linuxcnc = require()
    plan, program = tmp_path / "plan.csv", tmp_path / "plan.ngc"
    done = subprocess.run([sys.executable, "-m", "compd", "testplan", "--max-rpm", "12000", "--hours", str(HOURS),
                           "--time-constant-min", "30", "--out", str(plan), "--gcode", "linuxcnc", "--program",
                           str(program), "--probe-call", "(probe)"], capture_output=True, text=True, env=env(),
                          timeout=120)
    assert done.returncode == 0, done.stderr
    program.write_text(_scaled(program.read_text(), SPEEDUP))
    residual = tmp_path / "residual.csv"
    bench = {"devices": [
        {"kind": "linuxcnc_hal", "name": "lcnc", "axes": ["z"]},
        {"kind": "pt100_modbus", "name": "temps", "port": 0, "plant": "spindle", "channels": [{"name": "T_xi"}]},
        {"kind": "plant", "name": "spindle", "scenario": str(ROOT / "hil_sim/scenarios/spindle_demo.yaml"),
         "port": 0, "speedup": SPEEDUP, "duration_s": HOURS * 3600 + 1800, "log_path": str(residual),
         "log_period_s": 10.0, "cnc": "lcnc", "cnc_axes": {"z": 0}},
    ]}
    with Sim() as sim:
        (tmp_path / "bench.yaml").write_text(yaml.safe_dump(bench))
        serve, ports = start_serve(tmp_path / "bench.yaml")
        compd = None
        try:
            config = {
                "loop": {"period_s": 0.005},
                "sources": [
                    {"kind": "modbus", "name": "pt", "transport": "tcp", "host": "127.0.0.1", "port": ports["temps"],
                     "poll_period_s": 0.05, "timeout_s": 0.5, "stale_after_s": 2.0,
                     "channels": [{"name": "T_xi", "address": 0}]},
                    {"kind": "hal", "name": "cnc", "signals": [{"name": "speed_rpm", "pin": "spindle.0.speed-out"}]},
                ],
                "model": MODEL,
                "guard": {"max_abs_um": 63.0, "max_slew_um_per_s": 50.0, "stale_after_s": 2.0,
                          "signals": {"T_xi": {"min": 0.0, "max": 80.0}, "speed_rpm": {"min": 0.0, "max": 30000.0}}},
                "sink": {"kind": "linuxcnc", "axes": ["z"]},
                "status": {"path": "status.json", "period_s": 0.05},
            }
            cfg = tmp_path / "compd.yaml"
            cfg.write_text(yaml.safe_dump(config))
            err = tmp_path / "compd.err"
            with open(err, "w") as fh:
                compd = subprocess.Popen([sys.executable, "-m", "compd", "run", str(cfg)], cwd=tmp_path, env=env(),
                                         stdout=subprocess.DEVNULL, stderr=fh)
            status = tmp_path / "status.json"

            def running() -> dict | None:
                assert compd is not None and compd.poll() is None, err.read_text()
                try:
                    st = json.loads(status.read_text())
                except (OSError, ValueError):
                    return None
                return st if st["state"] == "running" and st["sink"]["link"] == "up" else None

            wait_for(running, "compd running with LinuxCNC's offsets up", timeout_s=120)
            sim.run_program(program)
            stat = sim.stat()
            seen, spun = [], False
            deadline = time.monotonic() + 600
            while True:  # the program runs: LinuxCNC's offset between two of compd's statuses, within 1 µm
                s1 = json.loads(status.read_text())
                time.sleep(0.1)
                applied_um = sim.getp("axis.z.eoffset") * 1000.0
                time.sleep(0.1)
                s2 = json.loads(status.read_text())
                before, after = s1["axes"]["z"]["correction_um"], s2["axes"]["z"]["correction_um"]
                if (before is not None and after is not None and abs(after - before) < 0.05
                        and s2["loop"]["cycles"] > s1["loop"]["cycles"] + 20):  # held still around the read
                    seen.append(applied_um - 0.5 * (before + after))
                spun = spun or sim.getp("spindle.0.speed-out") > 0
                stat.poll()
                if stat.interp_state == linuxcnc.INTERP_IDLE and spun:
                    break
                assert time.monotonic() < deadline, "the program did not end within 600 s"
            assert len(seen) > 20
            print(f"\nLinuxCNC's offset - compd's correction: {len(seen)} steady reads, largest"
                  f" {max(map(abs, seen)):.3f} um")
            assert max(map(abs, seen)) <= 1.0, seen
            compd.send_signal(signal.SIGTERM)
            assert compd.wait(60) == 0, err.read_text()
            assert abs(sim.getp("axis.z.eoffset")) < 0.15e-3  # the safe state: 0
        finally:
            if compd is not None and compd.poll() is None:
                compd.kill()
                compd.wait(30)
            serve_err = stop_serve(serve)
        report = residual_report(residual, t_from_s=3600.0)["z"]
        print(f"\nLinuxCNC closed loop: z RMS {report['rms_before_um']:.2f} -> {report['rms_after_um']:.2f} um"
              f" ({report.get('reduction_pct', float('nan')):.1f} %)")
        assert report["rms_before_um"] > 3.0, (report, serve_err[-2000:])
        assert report["rms_after_um"] < 0.5 * report["rms_before_um"], report

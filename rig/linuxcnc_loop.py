"""The closed loop on LinuxCNC: compd testplan's program on the controller, hil_sim's spindle at its speed.

compd acts through LinuxCNC's offsets.

`run` needs a LinuxCNC that runs, is on and homed (the test suite's headless sim mill, tests/linuxcnc/sim.py,
or a machine of yours: `controller` has `getp(pin)`, `run_program(path)` and `stat()`). It designs the thermal
test (`compd testplan`, `hours`), runs its LinuxCNC program with every dwell divided by the plant's
`speedup` (the plant's thermal time runs that much faster than the controller's), starts `hil_sim serve`
(the spindle turning at LinuxCNC's `spindle.0.speed-out`, its PT100 on Modbus TCP, the offset LinuxCNC
applies on `axis.z.eoffset` read from HAL: device `linuxcnc_hal`) and `compd run` (configs/linuxcnc_spindle.yaml's
loop: the ξ sensor over Modbus, the speed from HAL, the correction through the linuxcnc sink). While the program
runs it reads LinuxCNC's offset beside compd's correction (in reads where the correction held still: a read
through halcmd takes tens of ms); SIGTERM to compd must leave 0. The error at the tool is the plant's
residual log: its growth plus the offset LinuxCNC applied.

`in_process` runs the same plan on the same plant without LinuxCNC: `hil_sim log --plan`, replayed through
the same model and the linuxcnc sink's in-process emulation (`compd replay`).
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from hil_sim.devices.plant import residual_report
from rig.closedloop import ROOT, env, start_serve, stop_serve

SCENARIO = ROOT / "hil_sim" / "scenarios" / "spindle_demo.yaml"
MODEL = {  # the demo's ξ-point model of hil_sim's spindle (configs/demo.yaml)
    "kind": "xi_spindle",
    "inputs": ["T_xi", "speed_rpm"],
    "outputs": ["z"],
    "params": {
        "alpha_per_k": 13.6e-6,
        "length_mm": 164.71,
        "t0_c": None,
        "xi_mm": 55.2,
        "lift": {"k_um_per_rpm2": 2.611e-8, "speed_input": "speed_rpm"},
    },
}
GUARD = {
    "max_abs_um": 63.0,
    "max_slew_um_per_s": 50.0,
    "stale_after_s": 2.0,
    "signals": {"T_xi": {"min": 0.0, "max": 80.0}, "speed_rpm": {"min": 0.0, "max": 30000.0}},
}
SKIP_S = 3600.0  # the first plant hour (the plan's idle stretch) is not scored


def scaled(program: str, speedup: float) -> str:
    """The program with every dwell divided by `speedup`."""
    return re.sub(r"^G4 P([0-9.]+)$", lambda m: f"G4 P{float(m.group(1)) / speedup:.4f}", program, flags=re.M)


def plan(workdir: Path, hours: float) -> tuple[Path, Path]:
    """`compd testplan` for the spindle (12000 rpm, τ 30 min): (plan.csv, plan.ngc)."""
    csv, ngc = workdir / "plan.csv", workdir / "plan.ngc"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "compd",
            "testplan",
            "--max-rpm",
            "12000",
            "--hours",
            f"{hours:g}",
            "--time-constant-min",
            "30",
            "--out",
            str(csv),
            "--gcode",
            "linuxcnc",
            "--program",
            str(ngc),
            "--probe-call",
            "(probe)",
        ],
        capture_output=True,
        text=True,
        env=env(),
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"compd testplan: {done.stderr.strip()}")
    return csv, ngc


def run(controller: Any, workdir: Path, hours: float, speedup: float, timeout_s: float = 1800.0) -> dict[str, Any]:
    """The loop on LinuxCNC (see the module): the follow reads, compd's exit, the offset after, the residual."""
    from compd.io import hal_modules

    _, linuxcnc = hal_modules.load()
    _, ngc = plan(workdir, hours)
    ngc.write_text(scaled(ngc.read_text(), speedup))
    residual = workdir / "residual.csv"
    bench = {
        "devices": [
            {"kind": "linuxcnc_hal", "name": "lcnc", "axes": ["z"]},
            {"kind": "pt100_modbus", "name": "temps", "port": 0, "plant": "spindle", "channels": [{"name": "T_xi"}]},
            {
                "kind": "plant",
                "name": "spindle",
                "scenario": str(SCENARIO),
                "port": 0,
                "speedup": speedup,
                "duration_s": hours * 3600 + 1800,
                "log_path": str(residual),
                "log_period_s": 10.0,
                "cnc": "lcnc",
                "cnc_axes": {"z": 0},
            },
        ]
    }
    (workdir / "bench.yaml").write_text(yaml.safe_dump(bench))
    serve, ports = start_serve(workdir / "bench.yaml")
    compd: subprocess.Popen[bytes] | None = None
    out: dict[str, Any] = {"hours": hours, "speedup": speedup}
    try:
        config = {
            "loop": {"period_s": 0.005},
            "sources": [
                {
                    "kind": "modbus",
                    "name": "pt",
                    "transport": "tcp",
                    "host": "127.0.0.1",
                    "port": ports["temps"],
                    "poll_period_s": 0.05,
                    "timeout_s": 0.5,
                    "stale_after_s": 2.0,
                    "channels": [{"name": "T_xi", "address": 0}],
                },
                {"kind": "hal", "name": "cnc", "signals": [{"name": "speed_rpm", "pin": "spindle.0.speed-out"}]},
            ],
            # the guard's times are the loop's (wall) seconds, the plant's are `speedup` times faster: its
            # recovery after an input blip (5 s of plant time, as in process) shrinks with them
            "model": MODEL,
            "guard": {**GUARD, "recovery_s": 5.0 / speedup},
            "sink": {"kind": "linuxcnc", "axes": ["z"]},
            "status": {"path": "status.json", "period_s": 0.05},
        }
        cfg = workdir / "compd.yaml"
        cfg.write_text(yaml.safe_dump(config))
        err = workdir / "compd.err"
        with open(err, "w") as fh:
            compd = subprocess.Popen(
                [sys.executable, "-m", "compd", "run", str(cfg)],
                cwd=workdir,
                env=env(),
                stdout=subprocess.DEVNULL,
                stderr=fh,
            )
        status = workdir / "status.json"
        deadline = time.monotonic() + 120
        while True:  # compd running, LinuxCNC's offsets up
            if compd.poll() is not None:
                raise RuntimeError(f"compd run ended: {err.read_text()[-2000:]}")
            try:
                st = json.loads(status.read_text())
                if st["state"] == "running" and st["sink"]["link"] == "up":
                    break
            except (OSError, ValueError, KeyError):
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("compd's linuxcnc sink did not come up within 120 s")
            time.sleep(0.05)
        controller.run_program(ngc)
        stat = controller.stat()
        follow: list[float] = []
        spun = False
        deadline = time.monotonic() + timeout_s
        while True:  # the program runs: LinuxCNC's offset beside compd's correction, where it held still
            s1 = json.loads(status.read_text())
            time.sleep(0.1)
            applied_um = controller.getp("axis.z.eoffset") * 1000.0
            time.sleep(0.1)
            s2 = json.loads(status.read_text())
            before, after = s1["axes"]["z"]["correction_um"], s2["axes"]["z"]["correction_um"]
            if (
                before is not None
                and after is not None
                and abs(after - before) < 0.05
                and s2["loop"]["cycles"] > s1["loop"]["cycles"] + 20
            ):
                follow.append(applied_um - 0.5 * (before + after))
            spun = spun or controller.getp("spindle.0.speed-out") > 0
            stat.poll()
            if stat.interp_state == linuxcnc.INTERP_IDLE and spun:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"the program did not end within {timeout_s:g} s")
        out["follow_reads"] = len(follow)
        out["follow_max_um"] = max(map(abs, follow)) if follow else None
        compd.send_signal(signal.SIGTERM)
        out["compd_exit"] = compd.wait(60)
        out["eoffset_after_um"] = controller.getp("axis.z.eoffset") * 1000.0
    finally:
        if compd is not None and compd.poll() is None:
            compd.kill()
            compd.wait(30)
        out["serve_stderr"] = stop_serve(serve)[-2000:]
    out["z"] = residual_report(residual, t_from_s=SKIP_S)["z"]
    return out


def in_process(workdir: Path, hours: float) -> dict[str, Any]:
    """The same plan on the same plant, replayed in process through the same model and the linuxcnc sink's emulation."""
    csv, _ = plan(workdir, hours)
    day = workdir / "day.csv"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "hil_sim",
            "log",
            "--scenario",
            str(SCENARIO),
            "--plan",
            str(csv),
            "--out",
            str(day),
            "--rate-s",
            "10",
        ],
        capture_output=True,
        text=True,
        env=env(),
        timeout=600,
    )
    if done.returncode != 0:
        raise RuntimeError(f"hil_sim log: {done.stderr.strip()}")
    config = {
        "loop": {"clock": "sim", "period_s": 1.0},
        "sources": [{"kind": "replay", "name": "day", "path": str(day)}],
        "model": MODEL,
        "guard": {**GUARD, "stale_after_s": 60.0, "recovery_s": 5.0},
        "sink": {"kind": "linuxcnc", "axes": ["z"], "in_process": True},
    }
    cfg = workdir / "replay.yaml"
    cfg.write_text(yaml.safe_dump(config))
    report = workdir / "replay.json"
    done = subprocess.run(
        [sys.executable, "-m", "compd", "replay", str(cfg), "--log", str(day), "--report", str(report)],
        capture_output=True,
        text=True,
        env=env(),
        timeout=600,
    )
    if done.returncode != 0:
        raise RuntimeError(f"compd replay: {done.stderr.strip()}")
    return json.loads(report.read_text())

"""Bad input through the real command line: exit 2, exactly one line on stderr, never a traceback.

Each case runs `python -m compd` as a subprocess (as a user or a script runs it): paths it
cannot read or write, malformed numbers, empty and binary files, absurd log times, devices
that do not exist.
"""

from __future__ import annotations

import errno
import json
import subprocess
import sys

import numpy as np
import pytest

from compd.log import write_log
from tests.conftest import ROOT

SIM = """\
loop: {clock: sim, period_s: 1.0}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {seed: 3, segments: [{duration_s: 600, speed_rpm: 10000}]}
model: {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 13.6e-6, length_mm: 165.0}}
sink: {kind: pci1756}
"""

MODEL = """\
kind: mlr
inputs: [T1]
outputs: [x1]
params: {coef_um_per_k: [[2.0]], intercept_um: [0.0]}
"""

DEVICE = """\
loop: {{period_s: 0.01}}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {{seed: 3, segments: [{{duration_s: 100, speed_rpm: 10000}}]}}
  - {source}
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
sink: {{kind: pci1756}}
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    t = np.arange(50) * 10.0
    T1 = 20 + 0.01 * t
    write_log(d / "log.csv", ["t_s", "T1", "err_x1_um"], np.column_stack([t, T1, 2 * (T1 - 20)]))
    text = (d / "log.csv").read_text().splitlines()

    def with_t(name, row, value):
        lines = list(text)
        lines[row] = ",".join([value, *lines[row].split(",")[1:]])
        (d / name).write_text("\n".join(lines) + "\n")

    with_t("t_1e308.csv", 30, "1e308")
    with_t("t_inf.csv", 30, "inf")
    with_t("t_nan.csv", 30, "nan")
    gap = [text[0]] + [
        ",".join([str(float(r.split(",")[0]) + (5e10 if i >= 20 else 0.0)), *r.split(",")[1:]])
        for i, r in enumerate(text[1:])
    ]
    (d / "t_gap.csv").write_text("\n".join(gap) + "\n")
    (d / "model.yaml").write_text(MODEL)
    (d / "sim.yaml").write_text(SIM)
    (d / "binary.dat").write_bytes(b"\x00\x01\xff\xfe\x80 binary")
    (d / "empty.txt").write_text("")
    (d / "text.txt").write_text("hello\n")
    (d / "list.json").write_text("[1, 2]\n")
    (d / "shape.json").write_text(json.dumps({"schema": 1, "axes": 5}))
    (d / "deep.json").write_text(json.dumps({"schema": 1, "written_unix_s": 0, "axes": {"z": {"prediction_um": "x"}}}))
    (d / "afile").write_text("a regular file\n")
    (d / "adir").mkdir()
    for name, source in (
        ("can_unknown.yaml", "{kind: can, name: c, interface: nosuch, channel: can0, signals: [{name: T_a, id: 1}]}"),
        (
            "can_slcan.yaml",
            "{kind: can, name: c, interface: slcan, channel: /dev/ttyNOPE0, signals: [{name: T_a, id: 1}]}",
        ),
        (
            "can_serial.yaml",
            "{kind: can, name: c, interface: serial, channel: /dev/ttyNOPE0, signals: [{name: T_a, id: 1}]}",
        ),
        (
            "can_socketcan.yaml",
            "{kind: can, name: c, interface: socketcan, channel: nocan9, signals: [{name: T_a, id: 1}]}",
        ),
        ("dcon.yaml", "{kind: dcon, name: d, serial_port: /dev/ttyNOPE0, channels: [T_a]}"),
        (
            "rtu.yaml",
            "{kind: modbus, name: m, transport: rtu, serial_port: /dev/ttyNOPE0, channels: [{name: T_a, address: 0}]}",
        ),
    ):
        (d / name).write_text(DEVICE.format(source=source))
    return d


# (argv with {d} for the folder, words the one stderr line must contain)
CASES = [
    # outputs that cannot be written: refused before the work
    (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/adir"], ["adir", "--out", "folder"]),
    (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "/proc/x.yaml"], ["/proc/x.yaml", "--out"]),
    (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/afile/x.yaml"], ["afile/x.yaml", "--out"]),
    (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/missing/x.yaml"], ["missing/x.yaml", "--out"]),
    (["fit", "--kind", "all", "--log", "{d}/log.csv", "--out", "{d}/afile"], ["afile", "--out", "not a folder"]),
    (
        ["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/m.yaml", "--report", "/proc/r.json"],
        ["/proc/r.json", "--report"],
    ),
    (
        ["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/m.yaml", "--plot", "{d}/p.xyz"],
        ["p.xyz", "--plot", ".xyz"],
    ),
    (["predict", "{d}/model.yaml", "--log", "{d}/log.csv", "--out", "{d}/adir"], ["adir", "--out"]),
    (["predict", "{d}/model.yaml", "--log", "{d}/log.csv", "--out", "/proc/p.csv"], ["/proc/p.csv", "--out"]),
    (
        ["replay", "--model", "{d}/model.yaml", "--log", "{d}/log.csv", "--report", "/proc/r.json"],
        ["/proc/r.json", "--report"],
    ),
    (["replay", "--model", "{d}/model.yaml", "--log", "{d}/log.csv", "--report", "{d}/adir"], ["adir", "--report"]),
    (
        ["replay", "--model", "{d}/model.yaml", "--log", "{d}/log.csv", "--plot", "{d}/afile/p.png"],
        ["afile/p.png", "--plot"],
    ),
    (["run", "{d}/sim.yaml", "--json", "/proc/x.json"], ["/proc/x.json", "--json"]),
    (["run", "{d}/sim.yaml", "--json", "{d}/adir"], ["adir", "--json"]),
    (["bench", "--cycles", "10", "--json", "/proc/b.json"], ["/proc/b.json", "--json"]),
    (["docs", "--out", "/proc/x.md"], ["/proc/x.md", "--out"]),
    # an output in a folder that does not exist: every command with an output path, before the work
    *[
        (argv + [flag, "{d}/nofolder/" + name], ["nofolder/" + name, flag, "No such file or directory"])
        for argv, flag, name in [
            (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/m.yaml"], "--report", "r.json"),
            (["fit", "--kind", "mlr", "--log", "{d}/log.csv", "--out", "{d}/m.yaml"], "--plot", "p.png"),
            (["fit", "--kind", "all", "--log", "{d}/log.csv", "--out", "{d}/nofolder/all"], "--report", "r.json"),
            (["predict", "{d}/model.yaml", "--log", "{d}/log.csv"], "--out", "p.csv"),
            (["replay", "--model", "{d}/model.yaml", "--log", "{d}/log.csv"], "--report", "r.json"),
            (["replay", "--model", "{d}/model.yaml", "--log", "{d}/log.csv"], "--plot", "p.png"),
            (["run", "{d}/sim.yaml"], "--json", "r.json"),
            (["score", "{d}/model.yaml", "--log", "{d}/log.csv"], "--json", "s.json"),
            (["docs"], "--out", "c.md"),
        ]
    ],
    # log time: non-finite, absurd, absurd span
    (["replay", "--model", "{d}/model.yaml", "--log", "{d}/t_1e308.csv"], ["t_1e308.csv:31", "t_s"]),
    (["replay", "--model", "{d}/model.yaml", "--log", "{d}/t_inf.csv"], ["t_inf.csv:31", "t_s", "finite"]),
    (["replay", "--model", "{d}/model.yaml", "--log", "{d}/t_nan.csv"], ["t_nan.csv:31", "t_s", "finite"]),
    (["replay", "--model", "{d}/model.yaml", "--log", "{d}/t_gap.csv"], ["t_gap.csv:22", "t_s"]),
    (["predict", "{d}/model.yaml", "--log", "{d}/t_1e308.csv", "--out", "{d}/p.csv"], ["t_1e308.csv:31", "t_s"]),
    # status files
    (["status", "--status", "{d}/binary.dat"], ["binary.dat", "not a status file"]),
    (["status", "--status", "{d}/empty.txt"], ["empty.txt", "not a status file"]),
    (["status", "--status", "{d}/adir"], ["adir", "cannot read"]),
    (["status", "--status", "{d}/text.txt"], ["text.txt", "not a status file"]),
    (["status", "--status", "{d}/list.json"], ["list.json", "not a compd status file"]),
    (["status", "--status", "{d}/shape.json"], ["shape.json", "axes", "expected an object"]),
    (["status", "--status", "{d}/deep.json"], ["deep.json", "not a compd status file"]),
    # malformed numbers
    (["run", "{d}/sim.yaml", "--duration", "nan"], ["--duration", "finite"]),
    (["run", "{d}/sim.yaml", "--duration", "inf"], ["--duration", "finite"]),
    (["run", "{d}/sim.yaml", "--duration", "-5"], ["--duration", "> 0"]),
    (["run", "{d}/sim.yaml", "--duration", "0"], ["--duration", "> 0"]),
    (["run", "{d}/sim.yaml", "--duration", "soon"], ["--duration", "not a number"]),
    (["encode", "nan", "0"], ["C1_UM", "finite"]),
    (["decode", "0x0101", "--lsb-um", "nan"], ["--lsb-um", "finite"]),
    (["bench", "--cycles", "10", "--period-ms", "nan"], ["--period-ms", "finite"]),
    (["bench", "--cycles", "10", "--period-ms", "0"], ["--period-ms", "> 0"]),
    # devices that do not exist: the config file, line and key
    (["check-config", "{d}/can_unknown.yaml"], ["can_unknown.yaml:7:", "sources[1].interface", "nosuch"]),
    (["run", "{d}/can_unknown.yaml", "--duration", "1"], ["can_unknown.yaml:7:", "sources[1].interface"]),
    (["run", "{d}/can_slcan.yaml", "--duration", "1"], ["can_slcan.yaml:7:", "sources[1].channel", "/dev/ttyNOPE0"]),
    (["run", "{d}/can_serial.yaml", "--duration", "1"], ["can_serial.yaml:7:", "sources[1].channel", "/dev/ttyNOPE0"]),
    # socketcan: `channel` where the kernel has SocketCAN and no such device, `interface` where it has none
    (["run", "{d}/can_socketcan.yaml", "--duration", "1"], ["can_socketcan.yaml:7:", "sources[1]."]),
    (["run", "{d}/dcon.yaml", "--duration", "1"], ["dcon.yaml:7:", "sources[1].serial_port", "/dev/ttyNOPE0"]),
    (["run", "{d}/rtu.yaml", "--duration", "1"], ["rtu.yaml:7:", "sources[1].serial_port", "/dev/ttyNOPE0"]),
]


@pytest.mark.parametrize(("argv", "words"), CASES, ids=[" ".join(c[0]).replace("{d}/", "") for c in CASES])
def test_bad_input_is_exit_2_one_line(files, argv, words):
    argv = [a.replace("{d}", str(files)) for a in argv]
    proc = subprocess.run([sys.executable, "-m", "compd", *argv], capture_output=True, text=True, timeout=120, cwd=ROOT)
    err = proc.stderr
    assert "Traceback" not in err and "internal error" not in err, err
    assert proc.returncode == 2, (proc.returncode, err, proc.stdout[-500:])
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for w in words:
        assert w.replace("{d}", str(files)) in lines[0], (w, lines[0])
    assert "cycles" not in proc.stdout  # refused before the loop ran, not after
    assert not (files / "nofolder").exists()  # nothing written (nor a folder made) before the refusal


def test_refused_outputs_are_not_left_behind(files, tmp_path):
    """The write check does not leave an empty file where the work then failed."""
    out = tmp_path / "m.yaml"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "compd",
            "fit",
            "--kind",
            "mlr",
            "--log",
            str(files / "log.csv"),
            "--out",
            str(out),
            "--report",
            "/proc/r.json",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 2 and not out.exists()


@pytest.mark.parametrize(
    ("exc", "key"),
    [
        (OSError(errno.ENODEV, "No such device"), "channel"),  # socketcan: no such interface can0
        (OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol"), "interface"),  # no SocketCAN
    ],
)
def test_can_open_errors_name_the_key(monkeypatch, tmp_path, exc, key):
    """python-can's errors for a missing socketcan device map to the config's key (the kernel
    here has no SocketCAN, so the device case is driven through can.Bus)."""
    import can

    from compd.config import load_config
    from compd.core.errors import BadInput
    from compd.daemon.app import App

    def no_bus(**kw):
        raise exc

    monkeypatch.setattr(can, "Bus", no_bus)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        DEVICE.format(source="{kind: can, name: c, interface: socketcan, channel: can0, signals: [{name: T_a, id: 1}]}")
    )
    app = App(load_config(cfg))
    with pytest.raises(BadInput) as e:
        app.open()
    assert str(e.value).startswith(f"{cfg}:7: sources[1].{key}: cannot open CAN")

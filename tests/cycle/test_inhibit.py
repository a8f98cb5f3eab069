"""The machine inhibits compensation or an axis awaits its reference: the correction ramps to 0 at the slew and back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.config import load_config
from compd.core.config import GuardConfig, InhibitConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.cycle.guard import Guard
from compd.cycle.inhibit import INHIBITED, NONE, WAITING, Inhibit
from compd.daemon.app import App
from compd.plc.fanuc_pmc import FanucPmc
from compd.service.status import render, snapshot
from hil_sim.devices.modbus_server import ModbusServerThread

SLEW = 10.0  # µm/s
INHIBIT_REG, INHIBIT_BIT = 105, 2  # Y5.2: the ladder's "compensation inhibit"
REF_REG, REF_BIT = 106, 0  # Y6.0: Z referenced
TEMP_REG = 210  # R10: T_xi × 10
TARGET_UM = -13.6e-6 * 165.0 * 1000.0 * 10.0  # ξ spindle at +10 K: -22.44 µm correction


def _guard_with_hold(slew: float = SLEW) -> Guard:
    frame = Frame([])
    g = Guard(GuardConfig(max_slew_um_per_s=slew), ["z"], frame, [])
    return g


def test_guard_ramps_a_held_axis_to_zero_at_the_slew_and_back(caplog):
    from compd.cycle.publish import with_causes
    from compd.daemon.host import log_guard_event

    g = _guard_with_hold()
    pred = np.array([20.0])  # target −20 µm
    t, dt = 0.0, 0.01
    out = []
    for k in range(700):
        g.hold[0] = INHIBITED if 250 <= k < 450 else NONE
        g.update(pred, True, t)
        out.append(float(g.out_um[0]))
        t += dt
    c = np.array(out)
    assert np.max(np.abs(np.diff(c))) <= SLEW * dt + 1e-12  # never a step
    assert c[249] == pytest.approx(-20.0)
    assert c[250] == pytest.approx(-20.0 + SLEW * dt)  # the first held cycle: one slew step
    assert c[449] == pytest.approx(0.0, abs=1e-9)  # 200 cycles × 0.1 µm
    assert c[450] == pytest.approx(-SLEW * dt, abs=1e-9)  # released: back at the slew
    assert c[-1] == pytest.approx(-20.0)
    assert [e[2:] for e in g.events] == [("held", "inhibited"), ("released", "inhibited")]
    assert g.get_status()["z"]["inhibit"] is None
    with caplog.at_level("INFO", logger="compd"):
        for ev in with_causes(g.events, []):
            log_guard_event(*ev)
    assert [r.event for r in caplog.records] == ["axis_held", "axis_released"]
    assert caplog.records[0].getMessage() == "z held: inhibited"


def test_inhibit_reads_bits_fail_safe_and_names_unknown_signals():
    frame = Frame(["inh", "ref"])
    cfg = InhibitConfig(signal="inh", axes={"z": {"referenced": "ref"}})
    inh = Inhibit(cfg, ["z", "x"], frame)
    hold = np.zeros(2, dtype=np.uint8)
    frame.set(0, 0.0, Quality.GOOD, 0.0)
    frame.set(1, 0.0, Quality.GOOD, 0.0)
    inh.evaluate(frame, 0.1, hold)
    assert hold.tolist() == [WAITING, NONE]
    frame.set(1, 1.0, Quality.GOOD, 0.1)
    inh.evaluate(frame, 0.2, hold)
    assert hold.tolist() == [NONE, NONE]
    inh.evaluate(frame, 5.0, hold)  # both samples stale (1 s): inhibited, not referenced
    assert hold.tolist() == [INHIBITED, INHIBITED]
    frame.set(0, 0.0, Quality.COMMS_LOST, 5.0)
    frame.set(1, 1.0, Quality.GOOD, 5.0)
    inh.evaluate(frame, 5.0, hold)
    assert hold.tolist() == [INHIBITED, INHIBITED]
    inv = Inhibit(InhibitConfig(signal="inh", invert=True), ["z"], frame)  # an enable bit
    frame.set(0, 1.0, Quality.GOOD, 5.0)
    inv.evaluate(frame, 5.0, hold[:1])
    assert hold[0] == NONE
    with pytest.raises(BadInput) as e:
        Inhibit(InhibitConfig(axes={"z": {"signal": "nope"}}), ["z"], frame)
    assert e.value.path == "inhibit.axes.z.signal"


def test_inhibit_axis_must_be_a_model_output(tmp_path: Path):
    path = _config(tmp_path, port=1502)
    doc = yaml.safe_load(path.read_text())
    doc["inhibit"]["axes"] = {"y": {"referenced": "z_ref"}}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(BadInput) as e:
        load_config(path)
    assert e.value.path == "inhibit.axes.y" and e.value.line is not None


def _config(tmp_path: Path, port: int) -> Path:
    doc = {
        "loop": {"period_s": 0.01},
        "sources": [
            {
                "kind": "modbus",
                "name": "pmc",
                "host": "127.0.0.1",
                "port": port,
                "poll_period_s": 0.02,
                "timeout_s": 0.5,
                "channels": [
                    {"name": "T_xi", "address": TEMP_REG},
                    {"name": "cnc_inhibit", "address": INHIBIT_REG, "bit": INHIBIT_BIT},
                    {"name": "z_ref", "address": REF_REG, "bit": REF_BIT},
                ],
            }
        ],
        "model": {
            "kind": "xi_spindle",
            "inputs": ["T_xi"],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
        },
        "guard": {"max_slew_um_per_s": SLEW, "stale_after_s": 2.0},
        "inhibit": {"signal": "cnc_inhibit", "stale_after_s": 2.0, "axes": {"z": {"referenced": "z_ref"}}},
        "sink": {"kind": "pci1756"},
        "console": {"period_s": 0},
    }
    p = tmp_path / "inhibit.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def _set_bit(pmc: FanucPmc, reg: int, bit: int, on: bool) -> None:
    v = pmc.read_registers(reg, 1)[0]
    pmc.write_registers(reg, [(v | (1 << bit)) if on else (v & ~(1 << bit))])


def test_pmc_bits_over_modbus_hold_the_axis_and_ramp_at_the_slew(tmp_path: Path):
    """The CNC's PMC, served over Modbus TCP on 127.0.0.1: Z waits at 0 until its reference
    bit comes on, then ramps to the model's correction; the inhibit bit set mid-run ramps it
    to 0 at the slew, and releasing it ramps it back. Every step is within the slew of the
    time the guard licensed; the sequence is driven by what the loop reports, not by time."""
    pmc = FanucPmc()
    pmc.write_registers(TEMP_REG, [300])  # 30.0 °C: +10 K on t0
    trace: list[tuple[float, float, str | None, bool]] = []
    phase = {"name": "unreferenced", "cycles": 0}
    shown: list[str] = []

    def controller(loop, now: float) -> None:
        g = loop.guard
        st = g.get_status()["z"]
        trace.append((now, float(g.out_um[0]), st["inhibit"], bool(g.enable[0])))
        phase["cycles"] += 1
        name, out = phase["name"], float(g.out_um[0])
        if name == "unreferenced" and phase["cycles"] == 90:  # what `compd status` shows meanwhile
            shown.append(render(snapshot(loop, state="running", observe=False), True, ""))
        if name == "unreferenced" and phase["cycles"] >= 100:  # 1 s of loop time waiting at 0
            _set_bit(pmc, REF_REG, REF_BIT, True)
            phase.update(name="referenced", cycles=0)
        elif name == "referenced" and out == pytest.approx(TARGET_UM, abs=1e-9):
            _set_bit(pmc, INHIBIT_REG, INHIBIT_BIT, True)
            phase.update(name="inhibited", cycles=0)
        elif name == "inhibited" and out == 0.0 and phase["cycles"] > 20:
            _set_bit(pmc, INHIBIT_REG, INHIBIT_BIT, False)
            phase.update(name="released", cycles=0)
        elif name == "released" and out == pytest.approx(TARGET_UM, abs=1e-9):
            loop.stop()

    with ModbusServerThread(pmc, port=0) as srv:
        app = App(load_config(_config(tmp_path, srv.port)))
        app.loop.observers.append(controller)
        app.open()
        try:
            app.loop.run(duration_s=60.0)  # a bound only: the controller stops the loop
        finally:
            app.close()
    assert phase["name"] == "released", f"stopped in phase {phase['name']}"
    t = np.array([r[0] for r in trace])
    c = np.array([r[1] for r in trace])
    holds = [r[2] for r in trace]
    # before the first poll the signals have no data (inhibited: fail safe); then waiting for
    # reference: at zero, disabled, and says so
    first_ref = holds.index(None)
    assert first_ref >= 100 and set(holds[:first_ref]) <= {"inhibited", "waiting for reference"}
    assert holds[first_ref - 1] == "waiting for reference"
    z_row = next(line for line in shown[0].splitlines() if line.startswith("z "))
    assert "waiting for reference" in z_row
    assert np.all(c[:first_ref] == 0.0) and not any(r[3] for r in trace[:first_ref])
    # the inhibit: reached 0, then back to the target
    inhibited = [i for i, h in enumerate(holds) if h == "inhibited" and i > first_ref]  # not the no-data start
    assert inhibited and c[inhibited[-1]] == 0.0 and c[inhibited[0] - 1] == pytest.approx(TARGET_UM)
    assert c[-1] == pytest.approx(TARGET_UM)
    # never a step: each change within the slew of the time between the cycles
    dt = np.diff(t)
    assert np.all(np.abs(np.diff(c)) <= SLEW * dt + 1e-9)
    # the ramp down took the slew's time, not one cycle
    assert t[inhibited[-1]] - t[inhibited[0]] >= abs(TARGET_UM) / SLEW - 0.05


def test_check_config_names_an_unknown_inhibit_signal(tmp_path: Path, capsys):
    from compd.cli import main

    text = (Path(__file__).parents[2] / "configs" / "inhibit_fanuc.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("{referenced: z_referenced}", "{referenced: z_refd}"))
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("inhibit.axes.z.referenced: 'z_refd' is not a signal of any source")
    assert f"{bad}:" in err and len(err.splitlines()) == 1


def test_replay_holds_off_where_the_log_says_the_machine_did(tmp_path: Path):
    """A log with the inhibit column: the replay ramps the correction to 0 at the slew where
    the machine inhibited it and back after; a log without it is replayed never held off."""
    from compd.commissioning.replay import replay_config
    from compd.log import write_log

    n = 400
    t = np.arange(n, dtype=float)
    temp = np.full(n, 30.0)
    inhibit = ((t >= 100) & (t < 200)).astype(float)
    err = np.full(n, -TARGET_UM)
    write_log(
        tmp_path / "held.csv", ["t_s", "T_xi", "cnc_inhibit", "err_z_um"], np.column_stack([t, temp, inhibit, err])
    )
    write_log(tmp_path / "plain.csv", ["t_s", "T_xi", "err_z_um"], np.column_stack([t, temp, err]))
    doc = {
        "sources": [{"kind": "replay", "name": "log", "path": "held.csv"}],
        "model": {
            "kind": "xi_spindle",
            "inputs": ["T_xi"],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
        },
        "guard": {"max_slew_um_per_s": 2.0},
        "inhibit": {"signal": "cnc_inhibit", "stale_after_s": 5.0},
        "sink": {"kind": "siemens"},
    }
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    res = replay_config(cfg, tmp_path / "held.csv")
    assert res.report["inhibit"] == "from the log"
    c = res.applied_um[:, 0]
    assert c[99] == pytest.approx(TARGET_UM, abs=0.1)
    assert abs(c[199]) < 1e-6  # 22.4 µm at 2 µm/s: held at 0 well before the release
    assert c[-1] == pytest.approx(TARGET_UM, abs=0.1)
    assert np.max(np.abs(np.diff(c))) <= 2.0 * 1.0 + 1e-6  # never faster than the slew, row to row
    plain = replay_config(cfg, tmp_path / "plain.csv")
    assert plain.report["inhibit"] == "not in the log: never held off"
    assert plain.applied_um[150, 0] == pytest.approx(TARGET_UM, abs=0.1)
    # the held rows count uncompensated: a worse score than the replay never held off
    assert res.report["axes"]["z"]["rms_after_um"] > plain.report["axes"]["z"]["rms_after_um"] + 5.0

"""The plant's probing schedule: at its plant times it measures the residual plus σ-sized noise and
publishes it through the CNC's probe-result block (read here over Modbus TCP, as compd would)."""

from __future__ import annotations

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from compd.plc.fanuc_pmc import COMMAND, FanucPmc
from compd.plc.probe_block import decode_result
from compd.plc.siemens_nc import SiemensNc
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.plant import PlantDevice
from hil_sim.logcmd import load_plant
from hil_sim.scenario import SCENARIOS


def _spindle(**kw) -> tuple[PlantDevice, FanucPmc]:
    plant = load_plant(str(SCENARIOS / "spindle_unseen.yaml"), 1)
    dev = PlantDevice(plant, lockstep=True, duration_s=7200.0, **kw)
    pmc = FanucPmc()
    dev.attach_cnc(pmc, "fanuc_pmc", {"z": 0, "radial": 1}, on_plant_clock=True)
    return dev, pmc


def test_probes_at_the_schedule_measure_the_residual_with_sigma_noise():
    dev, pmc = _spindle(probe_every_s=60.0, probe_sigma_um=0.5, probe_seed=3)
    pmc.write_registers(COMMAND, [4, 0])  # the CNC applies +4 um on z: the residual includes it
    dev.start()
    with ModbusServerThread(pmc, port=0) as srv:
        client = ModbusTcpClient("127.0.0.1", port=srv.port)
        client.connect()
        try:
            dev.run_to(61.0)
            r = decode_result(client.read_holding_registers(500, count=8, device_id=1).registers)
        finally:
            client.close()
    assert r is not None and r.seq == 1 and r.axis == 0 and r.sigma_um == 0.5 and r.position_mm is None
    ((t, axis, d, residual),) = dev.probes
    assert (t, axis) == (60.0, "z") and r.deviation_um == pytest.approx(d, abs=1e-3)
    dev.run_to(7200.0)
    dev.stop()
    times = [p[0] for p in dev.probes]
    assert times == pytest.approx([60.0 * k for k in range(1, 120)])  # the plant ends at 7200 s
    assert [p[1] for p in dev.probes[:4]] == ["z", "radial", "z", "radial"]  # one axis per cycle, in turn
    noise = np.array([p[2] - p[3] for p in dev.probes])
    assert 0.35 < noise.std() < 0.65 and abs(noise.mean()) < 0.2
    assert pmc.probe.published == 119 and decode_result(pmc.read_registers(500, 8)).seq == 119
    # the same seed without the CNC's +4 um: the same noise, and z's residual 4 um less
    dev2, _ = _spindle(probe_every_s=60.0, probe_sigma_um=0.5, probe_seed=3)
    dev2.start()
    dev2.run_to(600.0)
    dev2.stop()
    assert [p[2] - p[3] for p in dev2.probes] == pytest.approx([p[2] - p[3] for p in dev.probes[:9]], abs=1e-12)
    for p1, p2 in zip(dev.probes[:9], dev2.probes, strict=True):
        assert p1[3] - p2[3] == pytest.approx(4.0 if p1[1] == "z" else 0.0, abs=1e-9)


def test_outliers_and_positions_through_a_siemens_nc():
    plant = load_plant(str(SCENARIOS / "feed_axis_unseen.yaml"), 1)
    dev = PlantDevice(
        plant, lockstep=True, duration_s=3600.0, probe_every_s=300.0, probe_sigma_um=0.0, probe_outliers=[[900.0, 25.0]]
    )
    nc = SiemensNc(axes=1)
    dev.attach_cnc(nc, "siemens_nc", None, on_plant_clock=True)
    dev.start()
    dev.run_to(3600.0)
    dev.stop()
    assert [p[0] for p in dev.probes] == pytest.approx([300.0 * k for k in range(1, 12)])
    extra = [p[2] - p[3] for p in dev.probes]
    assert extra[2] == pytest.approx(25.0) and all(e == pytest.approx(0.0) for i, e in enumerate(extra) if i != 2)
    r = decode_result(nc.read_registers(1000, 8))
    assert r.position_mm is not None and r.sigma_um is None  # the feed axis has a position; σ 0: not given


def test_probing_config_errors():
    plant = load_plant(str(SCENARIOS / "spindle_unseen.yaml"))
    with pytest.raises(ValueError, match="probe_every_s"):
        PlantDevice(plant, probe_every_s=0.0)
    with pytest.raises(ValueError, match="probe_axes"):
        PlantDevice(plant, probe_every_s=60.0, probe_axes=["q"])
    with pytest.raises(ValueError, match="needs a cnc"):
        PlantDevice(plant, lockstep=True, probe_every_s=60.0).start()

"""The plant device in lockstep: it holds its time until told to run to a later one (Modbus FC23
from compd's LockstepPlantClock), publishes once per step request, and the sink's queued writes
are acknowledged by the CNC before the plant moves."""

from __future__ import annotations

import numpy as np

from compd.io.modbus_link import ModbusLink
from compd.plc.fanuc_pmc import APPLIED, COMMAND, FanucPmc
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.plant import PlantDevice
from hil_sim.logcmd import load_plant
from hil_sim.plant_clock import LockstepPlantClock
from hil_sim.scenario import SCENARIOS


class _Sink:
    """The part of a sink the clock uses: what the device holds read back, flush = the link's drain."""

    def __init__(self, link: ModbusLink) -> None:
        self.link = link

    def await_held(self, timeout_s: float) -> bool:
        return self.link.await_held(timeout_s)

    def flush(self, timeout_s: float) -> bool:
        return self.link.drain(timeout_s)


def test_plant_holds_its_time_until_the_clock_runs_it_and_sees_every_write_first(tmp_path):
    plant = load_plant(str(SCENARIOS / "spindle_unseen.yaml"))
    dev = PlantDevice(plant, lockstep=True, duration_s=60.0, log_path=tmp_path / "r.csv", log_period_s=1.0)
    pmc = FanucPmc()
    dev.attach_cnc(pmc, "fanuc_pmc", {"z": 0}, on_plant_clock=True)
    dev.start()
    with ModbusServerThread(dev, port=0) as psrv, ModbusServerThread(pmc, port=0) as csrv:
        link = ModbusLink("127.0.0.1", csrv.port, name="t")
        link.start()
        clock = LockstepPlantClock("127.0.0.1", psrv.port)
        clock.start()
        try:
            clock.bind(_Sink(link), [])
            assert clock.now() == 0.0
            assert plant.t_s == 0.0  # no wall-time pace: the plant waits
            for k, shift_um in enumerate([0, 3, 6, 9, 9, 9], start=1):
                link.submit(COMMAND, [shift_um])  # what a cycle at t = 4(k-1) wrote
                clock.wait_until(4.0 * k)
                assert clock.now() == 4.0 * k == plant.t_s
                # the PMC scanned the write on plant time before the plant stepped on
                assert pmc.mem[APPLIED] == shift_um
            clock.wait_until(100.0)  # past the duration: the plant stops at its end
            assert clock.now() == 60.0 and clock.finished
        finally:
            clock.stop()
            link.stop()
    dev.stop()
    rows = np.loadtxt(tmp_path / "r.csv", delimiter=",", skiprows=1)
    # the cycle at t = 4 s wrote 3 um: the plant's step from 4 s on applies it, not earlier
    applied = dict(zip(rows[:, 0], rows[:, 3], strict=True))
    assert applied[3.0] == 0.0 and applied[4.0] == applied[7.0] == 3.0 and applied[8.0] == 6.0


def test_speed_up_plant_refuses_the_run_to_registers():
    plant = load_plant(str(SCENARIOS / "spindle_unseen.yaml"))
    dev = PlantDevice(plant, speedup=100.0)
    assert dev.write_registers(4, [0, 1000]) is False
    assert plant.t_s == 0.0

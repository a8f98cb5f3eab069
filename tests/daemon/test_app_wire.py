"""The daemon end to end over real wires: a Modbus TCP PT100 module in, the PMC over Modbus TCP out."""

from __future__ import annotations

import threading

import numpy as np
import yaml

from compd.config import load_config
from compd.daemon.app import App
from compd.plc.fanuc_pmc import FanucPmc
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from hil_sim.devices.scan import PmcScanThread

# 4 K above T0: error α L ΔT = 13.6e-6 × 165 mm × 4 K = 8.98 µm; correction −8.98 µm
WANT_UM = -13.6e-6 * 165.0 * 1000.0 * 4.0


def test_run_loop_reads_modbus_and_drives_pmc(tmp_path):
    tx = Pt100Transmitter(["T_xi"], [24.0])
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as pt, ModbusServerThread(pmc, port=0) as plc:
            cfg = tmp_path / "c.yaml"
            cfg.write_text(
                yaml.safe_dump(
                    {
                        "loop": {"period_s": 0.002},
                        "sources": [
                            {
                                "kind": "modbus",
                                "name": "pt",
                                "port": pt.port,
                                "poll_period_s": 0.02,
                                "channels": [{"name": "T_xi", "address": 0}],
                            }
                        ],
                        "model": {
                            "kind": "xi_spindle",
                            "inputs": ["T_xi"],
                            "outputs": ["z"],
                            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
                        },
                        "guard": {"max_slew_um_per_s": 100.0},
                        "sink": {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": plc.port, "max_step_um": 5},
                    }
                )
            )
            app = App(load_config(cfg), duration_s=10.0)
            seen: list[float] = []
            done = threading.Event()

            def watch(loop, now):
                if not done.is_set() and abs(pmc.applied_um()[0] - WANT_UM) <= 1.5:
                    seen.append(now)
                    done.set()
                    loop.stop()

            app.loop.cycle_hooks.append(watch)
            result = app.run()  # stops itself once the PMC applies the correction, or after 10 s
            # within the codec's dead-band (plus ½ LSB) of the wanted correction
            assert seen, f"the PMC never applied the correction: {result['faults']}"
            assert pmc.alarms() == 0
            # at exit the sink walked the shift back to zero in allowed steps
            assert pmc.applied_um() == [0.0, 0.0]
    finally:
        scan.stop()


def test_a_late_cycle_never_spends_the_pause_s_slew_at_once(tmp_path):
    """A pause of the daemon shorter than the loop's stall threshold (here 0.15 s at a 2 ms period):
    the next cycle moves the output by at most two periods' slew, never the pause's worth at once."""
    from tests.service_helpers import sim_config

    app = App(load_config(sim_config(tmp_path, period_s=0.002)), duration_s=1.0)
    try:
        guard = app.guard
        slew = guard.cfg.max_slew_um_per_s
        pred = np.full(len(guard.out_um), 50.0)
        guard.update(pred, True, 0.0)
        guard.update(pred, True, 0.002)
        before = guard.out_um.copy()
        guard.update(pred, True, 0.152)  # 150 ms late
        assert np.abs(guard.out_um - before).max() <= 2 * 0.002 * slew + 1e-12
        assert np.abs(guard.out_um - before).max() > 0.0
    finally:
        app.close()

"""A headless LinuxCNC sim mill (tests/linuxcnc/sim.py) for compd's tests: it starts homed, a HAL component of
the test process moves Z through external offsets, a G-code program runs, and it stops leaving nothing.

Every wait is a condition with a generous deadline (these run in `make test`, beside other load)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from tests.linuxcnc.sim import (
    Sim,
    SimError,
    linuxcnc_tmp_files,
    processes,
    require,
    shm_keys_left,
    wait_for,
)

TOL_MM = 1e-6  # the offset settles 6e-8 mm short of counts x scale (the planner's end of move)
# the programs of a running LinuxCNC (`display.py` is the Sim's display script)
RUNNING = {"linuxcnc", "linuxcncsvr", "rtapi_app", "milltask", "io", "display.py"}


def left_behind(sim: Sim) -> list[str]:
    """What of `sim`'s LinuxCNC is still there: processes, shared memory, LinuxCNC's /tmp files, the folder."""
    out = [f"process {name} {pid}" for pid, name in processes(None, with_token=sim.token)]
    out += [f"shm key {key:#x}" for key in shm_keys_left()]
    out += [f"/tmp/{name}" for name in sorted(linuxcnc_tmp_files())]
    out += [str(sim.folder)] if sim.folder.exists() else []
    return out


def test_the_sim_starts_homed_stops_leaving_nothing_and_starts_again():
    _, linuxcnc = require()
    for run in (1, 2):  # the second right after the first
        with Sim() as sim:
            stat = sim.stat()
            assert stat.homed[:3] == (1, 1, 1)
            assert stat.task_state == linuxcnc.STATE_ON
            assert stat.motion_mode == linuxcnc.TRAJ_MODE_TELEOP
            assert {name for _, name in processes(None, with_token=sim.token)} >= RUNNING
            assert sim.ini.is_file() and "display: homed (1, 1, 1)" in sim.log.read_text()
        assert left_behind(sim) == []
        print(f"sim {run}: start + home {sim.start_s:.2f} s, stop {sim.stop_s:.2f} s")


def test_a_component_of_the_test_process_offsets_z_by_counts_times_scale():
    hal, _ = require()
    with Sim() as sim:
        comp = hal.component("compdtest")
        try:
            comp.newpin("z.eoffset-counts", hal.HAL_S32, hal.HAL_OUT)
            comp.newpin("z.eoffset-enable", hal.HAL_BIT, hal.HAL_OUT)
            comp.newpin("z.eoffset-scale", hal.HAL_FLOAT, hal.HAL_OUT)
            comp.newpin("z.eoffset", hal.HAL_FLOAT, hal.HAL_IN)
            comp.ready()
            for pin in ("counts", "enable", "scale"):
                sim.halcmd("net", f"compdtest-{pin}", f"compdtest.z.eoffset-{pin}", f"axis.z.eoffset-{pin}")
            sim.halcmd("net", "compdtest-eoffset", "axis.z.eoffset", "compdtest.z.eoffset")
            stat = sim.stat()

            def z_at(mm: float) -> bool:
                stat.poll()
                return (
                    abs(sim.getp("axis.z.eoffset") - mm) < TOL_MM
                    and abs(comp["z.eoffset"] - mm) < TOL_MM
                    and abs(stat.actual_position[2] - mm) < TOL_MM
                )

            comp["z.eoffset-scale"] = 1e-4
            comp["z.eoffset-enable"] = True
            comp["z.eoffset-counts"] = 100
            began = time.monotonic()
            wait_for(lambda: z_at(0.010), "axis.z.eoffset, the in-pin and Z at 0.010 mm")
            print(f"counts 100 x 1e-4 mm: Z at 0.010 mm after {time.monotonic() - began:.2f} s")
            comp["z.eoffset-counts"] = 0
            wait_for(lambda: z_at(0.0), "axis.z.eoffset, the in-pin and Z back at 0")

            comp["z.eoffset-counts"] = 100
            wait_for(lambda: z_at(0.010), "Z at 0.010 mm again")
        finally:
            comp.exit()  # before the Sim stops: its shutdown SIGTERMs the process of every loaded component
        # the component gone with counts 100: its signals keep the values it left (they have no writer now),
        # so the offset stays where it was, and so does its target
        assert "compdtest" not in sim.halcmd("show", "comp")
        assert sim.getp("axis.z.eoffset-counts") == 100 and sim.getp("axis.z.eoffset-enable") is True
        assert abs(sim.getp("axis.z.eoffset-request") - 0.010) < 1e-12
        assert abs(sim.getp("axis.z.eoffset") - 0.010) < TOL_MM


def test_a_program_runs_the_spindle_through_a_dwell_and_ends(tmp_path):
    _, linuxcnc = require()
    program = tmp_path / "dwell.ngc"
    program.write_text("G21 G90\nS1000 M3\nG4 P2\nM5\nM2\n")
    with Sim() as sim:
        stat = sim.stat()
        sim.run_program(program)

        def spinning_in_the_program() -> bool:
            stat.poll()
            return sim.getp("spindle.0.speed-out") == 1000.0 and stat.interp_state != linuxcnc.INTERP_IDLE

        wait_for(spinning_in_the_program, "spindle.0.speed-out at 1000 during the dwell")
        assert stat.task_mode == linuxcnc.MODE_AUTO and stat.file == str(program)

        def ended() -> bool:
            stat.poll()
            return stat.interp_state == linuxcnc.INTERP_IDLE and stat.exec_state == linuxcnc.EXEC_DONE

        wait_for(ended, "the program's end (interp idle)")
        assert sim.getp("spindle.0.speed-out") == 0.0


def test_a_sim_whose_linuxcnc_was_killed_leaves_nothing_either():
    require()
    sim = Sim().start()
    try:
        os.killpg(sim.pid, signal.SIGKILL)  # a crash: rtapi_app and linuxcncsvr (sessions of their own) stay
        wait_for(lambda: sim.pid is None, "linuxcnc killed", 30)
        assert {"rtapi_app", "linuxcncsvr"} <= {name for _, name in processes(None, with_token=sim.token)}
    finally:
        sim.stop()
    assert left_behind(sim) == []
    with Sim() as again:
        assert again.stat().homed[:3] == (1, 1, 1)
    assert left_behind(again) == []


def test_a_component_left_loaded_fails_the_stop_not_the_test_run():
    hal, _ = require()
    sim = Sim().start()
    comp = hal.component("compdleft")
    try:
        comp.newpin("counts", hal.HAL_S32, hal.HAL_OUT)
        comp.ready()
        handler = signal.getsignal(signal.SIGTERM)
        with pytest.raises(SimError, match=r"still loaded when the Sim stopped: compdleft .*exit\(\) them"):
            sim.stop()  # LinuxCNC's `halcmd unload all` SIGTERMs this process meanwhile
        assert signal.getsignal(signal.SIGTERM) == handler
    finally:
        comp.exit()
        sim.stop()
    assert left_behind(sim) == []

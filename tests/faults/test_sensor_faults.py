"""Matrix rows for faults of the sensor itself, read over Modbus TCP from a hil_sim PT100 module."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from tests.faults.harness import (
    CLEAR_S,
    FAULT_S,
    SENSOR,
    WANT_UM,
    FaultRun,
    base_config,
    check,
    modbus_tcp_source,
    record,
)


@pytest.fixture
def module():
    """A one-channel PT100 module at 24 °C on Modbus TCP (127.0.0.1, a free port)."""
    tx = Pt100Transmitter([SENSOR], [24.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        yield tx, server


def test_sensor_burnout(tmp_path: Path, module) -> None:  # noqa: ANN001
    tx, server = module
    run = FaultRun(tmp_path, base_config(modbus_tcp_source(server.port), "hold"))
    run.at(FAULT_S, "fault", lambda: tx.set_fault(SENSOR, "burnout"))
    run.at(CLEAR_S, "clear", lambda: tx.set_fault(SENSOR, "none"))
    m = run.run(reasons=("burnout",))
    record("sensor_burnout", m, tmp_path)
    check(m, recovered=True)
    assert m.samples_lost == 0


def test_out_of_range_code(tmp_path: Path, module) -> None:  # noqa: ANN001
    tx, server = module
    run = FaultRun(tmp_path, base_config(modbus_tcp_source(server.port), "ramp_to_zero"))
    run.at(FAULT_S, "fault", lambda: tx.set_fault(SENSOR, "over"))
    m = run.run(reasons=("out_of_range",))
    record("out_of_range_code", m, tmp_path)
    check(m)
    # from where the output stood at the fault (−8.98 µm once settled) to zero at 20 µm/s, not faster
    tr, t_fault = run.trace, run.times["fault"]
    out_at_fault = next(o for t, o in zip(tr.t, tr.out, strict=True) if t >= t_fault)
    assert abs(out_at_fault) > 1.0  # the fault hit a correction to ramp down
    assert m.time_to_safe_s is not None and m.time_to_safe_s >= abs(out_at_fault) / 20.0 - 0.05


def test_out_of_configured_range(tmp_path: Path, module) -> None:  # noqa: ANN001
    tx, server = module
    # the value rises at a plausible rate until it passes the configured max (80 °C)
    t_rise = [None]

    def feed() -> list[float]:
        if t_rise[0] is None:
            return [24.0]
        return [min(24.0 + 150.0 * (time.monotonic() - t_rise[0]), 95.0)]

    tx.feed = feed
    cfg = base_config(modbus_tcp_source(server.port), "disable", limits={"max_rate_per_s": 500.0})
    run = FaultRun(tmp_path, cfg)
    run.at(FAULT_S, "fault", lambda: t_rise.__setitem__(0, time.monotonic()))
    m = run.run(reasons=("out_of_range",))
    record("out_of_configured_range", m, tmp_path)
    check(m)


def test_frozen_value(tmp_path: Path, module) -> None:  # noqa: ANN001
    tx, server = module
    frozen = [False]
    t_start = time.monotonic()
    last = [24.0]

    def feed() -> list[float]:  # a slow warm-up, 0.5 °C/s, until the transmitter sticks
        if not frozen[0]:
            last[0] = 24.0 + 0.5 * (time.monotonic() - t_start)
        return [last[0]]

    tx.feed = feed
    cfg = base_config(modbus_tcp_source(server.port), "disable", limits={"frozen_after_s": 0.4})
    run = FaultRun(tmp_path, cfg)
    run.at(FAULT_S, "fault", lambda: frozen.__setitem__(0, True))
    run.at(CLEAR_S, "clear", lambda: frozen.__setitem__(0, False))
    m = run.run(reasons=("frozen",))
    record("frozen_value", m, tmp_path)
    check(m, recovered=True)
    # not before frozen_after_s since the last change (0.1 °C steps come every 0.2 s at 0.5 °C/s)
    assert m.time_to_safe_s is not None and m.time_to_safe_s >= 0.4 - 0.2 - 0.05


def test_noisy_spike(tmp_path: Path, module) -> None:  # noqa: ANN001
    tx, server = module
    run = FaultRun(tmp_path, base_config(modbus_tcp_source(server.port), "hold"))
    run.at(FAULT_S, "fault", lambda: tx.set(SENSOR, 44.0))
    run.at(FAULT_S + 0.06, "clear", lambda: tx.set(SENSOR, 24.0))
    m = run.run(reasons=("implausible",))
    record("noisy_spike", m, tmp_path)
    check(m, recovered=True)
    # the correction never went towards the spike (44 °C would ask for −53.9 µm)
    peak = max(abs(o) for o in run.trace.out)
    assert peak <= abs(WANT_UM) + 0.5
    m.extra["peak_correction_um"] = peak
    record("noisy_spike", m, tmp_path)

"""The rows of the fault-injection matrix: id → (fault, transport, policy, expected behaviour).

Each row is one test in tests/faults/; docs/reliability.md has one table row per entry
(tests/faults/test_reliability_doc.py checks that).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Row:
    fault: str
    transport: str
    policy: str
    expected: str


MATRIX: dict[str, Row] = {
    "sensor_burnout": Row(
        "sensor burn-out (module sends its burn-out code)",
        "Modbus TCP",
        "hold",
        "input bad (burnout); axis holds its last correction; recovers by slewing when the sensor is back",
    ),
    "out_of_range_code": Row(
        "out-of-range code from the module",
        "Modbus TCP",
        "ramp_to_zero",
        "input bad (out_of_range); correction ramps to zero at ramp_um_per_s",
    ),
    "out_of_configured_range": Row(
        "value outside the configured range (95 °C > max 80 °C)",
        "Modbus TCP",
        "disable",
        "input bad (out_of_range); enable bit off, correction 0",
    ),
    "frozen_value": Row(
        "frozen value (transmitter stuck on one reading)",
        "Modbus TCP",
        "disable",
        "input bad (frozen) after frozen_after_s; enable bit off; back when the value moves",
    ),
    "noisy_spike": Row(
        "noisy spike (+20 °C for one poll)",
        "Modbus TCP",
        "hold",
        "input bad (implausible, rate limit); the spike never reaches the correction",
    ),
    "server_killed": Row(
        "Modbus server killed mid-run",
        "Modbus TCP",
        "ramp_to_zero",
        "input bad (comms_lost/stale); correction ramps to zero; compd keeps running",
    ),
    "server_restarted": Row(
        "Modbus server killed, then restarted",
        "Modbus TCP",
        "ramp_to_zero",
        "ramps to zero while down; reconnects; after recovery_s slews back to the model",
    ),
    "slow_answers": Row(
        "slow answers (0.3 s, past the 0.1 s timeout)",
        "Modbus TCP",
        "hold",
        "input bad (comms_lost/stale); axis holds",
    ),
    "exception_replies": Row(
        "Modbus exception replies (device failure)",
        "Modbus TCP",
        "hold",
        "input bad (comms_lost); axis holds",
    ),
    "rtu_garbage": Row(
        "garbage bytes on RTU",
        "Modbus RTU over a pty",
        "hold",
        "input bad (comms_lost); axis holds; reads resume when the line is clean",
    ),
    "rtu_crc_error": Row(
        "CRC errors on RTU",
        "Modbus RTU over a pty",
        "hold",
        "input bad (comms_lost); axis holds",
    ),
    "pty_closed": Row(
        "pseudo-terminal closed (socat killed)",
        "DCON over a pty",
        "disable",
        "input bad (comms_lost); enable bit off; compd keeps running",
    ),
    "can_silence": Row(
        "CAN bus silence",
        "CAN (python-can virtual)",
        "hold",
        "input bad (comms_lost); axis holds; back when frames return",
    ),
    "clock_jump": Row(
        "loop clock steps +60 s (a clock set ahead)",
        "Modbus TCP",
        "hold",
        "clock_jump event; no step: the cycle after the jump moves one period's slew at most",
    ),
    "disk_full": Row(
        "disk full under the data log (/dev/full)",
        "Modbus TCP",
        "hold",
        "one log_error line; compensation goes on unchanged; log rows dropped and counted",
    ),
    "kill9_restart": Row(
        "kill -9 of compd run, then restart",
        "Modbus TCP (separate process)",
        "hold",
        "state file resumed (T0 kept); log rows lost ≤ flush interval; the log stays valid",
    ),
    "bad_config_reload": Row(
        "bad config on SIGHUP reload",
        "Modbus TCP (separate process)",
        "hold",
        "reload rejected with one line naming the key; old config keeps running without a step",
    ),
    "modbus_malformed_reply": Row(
        "reply with extra registers / wrong function code from a non-pymodbus peer",
        "Modbus TCP (raw peer)",
        "hold",
        "input bad (comms_lost); axis holds; no register of another request is filled",
    ),
    "reload_unopenable": Row(
        "SIGHUP reload to a config that validates but cannot open (metrics port taken)",
        "Modbus TCP (separate process)",
        "hold",
        "reload_failed naming why; the old pipeline keeps compensating without a step; no exit",
    ),
    "reload_unreachable_sink": Row(
        "SIGHUP reload to a sink that cannot be reached (FANUC PMC, nothing listening)",
        "Modbus TCP (separate process)",
        "hold",
        "status and metrics show the sink's link down and the axis not enabled; compd keeps running",
    ),
}

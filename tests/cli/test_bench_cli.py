"""`compd bench` runs end to end against real devices, writes the bench JSON (docs/formats.md); no timing asserted."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rig import bench
from rig.bench import format_table


@pytest.mark.slow
def test_bench_writes_contract_json(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "compd",
            "bench",
            "--cycles",
            "400",
            "--naive-cycles",
            "30",
            "--load",
            "1",
            "--late-us",
            "1",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr
    assert "compd loop" in r.stdout and "naive loop" in r.stdout
    b = json.loads(out.read_text())
    assert b["period_ms"] == 2.0 and b["cycles"] == 400
    assert set(b["lateness_us"]) == {"p50", "p99", "p999", "max"}
    assert set(b["cycle_compute_us"]) == {"p50", "p99", "max"}
    assert isinstance(b["misses"], int)
    assert set(b["model_eval_us"]) == {"feed_axis", "lvr", "xi_spindle", "ar1", "mlr"}
    assert all(v > 0 for v in b["model_eval_us"].values())
    assert b["naive"]["cycles"] == 30
    # the naive loop sleeps a whole period after its work, so it can only fall behind
    assert b["naive"]["lateness_us"]["max"] > b["naive"]["lateness_us"]["p50"] >= 0
    assert b["rss_kb"]["end_kb"] > 0
    # the work between cycles is measured; the bare loop ran beside compd, and without it
    # (--bare-cycles 0) its column says so instead of showing zeros
    assert b["between_max_us"] > 0 and 0 <= b["between_overruns"] <= 400
    assert b["bare"]["cycles"] == 400 and "bare loop" in r.stdout
    table = format_table({**b, "bare": None})
    assert [ln.split()[-2] for ln in table.splitlines() if ln.startswith(("misses", "lateness max"))] == ["-", "-"]
    # compd's I/O threads are timed: every poll of the three modules and every PMC write
    io = b["io_us"]
    assert io["read"]["count"] >= 3 and 0 < io["read"]["p50"] <= io["read"]["p99"] <= io["read"]["max"] + 1
    # the loop emitted words; how many the PMC acknowledged within 0.8 s of wall time depends on
    # the machine's load, but an acknowledged write is timed both ways
    assert b["words_sent"] >= 1
    assert (io["write"]["count"] >= 1) == (io["output_latency"]["count"] >= 1)
    # the naive loop's own start-to-start interval is at least the period it sleeps
    assert b["naive"]["period_us"]["p50"] >= 2000
    # every cycle later than 1 us is matched with the other threads' work: each counted
    # once per thread at most, and every thread that recorded is a device's or compd's own
    assert b["load_processes"] == 1
    la = b["late_attribution"]
    assert la["threshold_us"] == 1.0 and 0 <= la["overlapping_none"] <= la["late_cycles"] <= 400
    assert all(0 <= v <= la["late_cycles"] for v in la["overlapping"].values())
    # the threads that can overlap: the three modules' pollers, the PMC's link, the status writer
    assert set(la["overlapping"]) <= {
        "poll-pt100_1",
        "poll-pt100_2",
        "poll-pt100_3",
        "modbus-link-fanuc_pmc",
        "compd-status",
        "compd-log",
    }


def test_bench_rejects_a_negative_load() -> None:
    r = subprocess.run([sys.executable, "-m", "compd", "bench", "--load", "-1"], capture_output=True, text=True)
    assert r.returncode == 2 and "--load" in r.stderr


def test_bench_rejects_zero_cycles() -> None:
    r = subprocess.run([sys.executable, "-m", "compd", "bench", "--cycles", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "--cycles" in r.stderr


@contextlib.contextmanager
def silent_device() -> Iterator[int]:
    """A port on 127.0.0.1 where the connection is accepted (the kernel's backlog) but nothing ever
    answers: a device that hangs. Closed on the way out."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(16)
        yield s.getsockname()[1]


def free_port() -> int:
    """A port nothing listens on (bound, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def devices_at(port: int) -> type:
    """A stand-in for rig.bench.Devices whose every device listens at `port`."""

    class At:
        def __init__(self, device_file: Path) -> None:
            self.ports = dict.fromkeys(("pt100_1", "pt100_2", "pt100_3", "pmc", "gantry"), port)

        def stop(self) -> None:
            pass

    return At


@pytest.mark.parametrize("listening", [True, False], ids=["accepts-never-answers", "nothing-listens"])
def test_bench_against_devices_that_do_not_answer_is_one_line_exit_1(listening, monkeypatch, capsys):
    """Before the loops, every device must answer one read: else one line naming the device, where it
    listens and what timed out, exit 1 (as compd output-test for a device that does not answer), not an
    internal error."""
    from compd.cli import main

    monkeypatch.setattr(bench, "CHECK_TIMEOUT_S", 0.5)
    with contextlib.ExitStack() as stack:
        port = stack.enter_context(silent_device()) if listening else free_port()
        monkeypatch.setattr(bench, "Devices", devices_at(port))
        t0 = time.monotonic()
        rc = main(["bench", "--cycles", "200", "--naive-cycles", "10", "--bare-cycles", "0"])
        took_s = time.monotonic() - t0
    err = capsys.readouterr().err
    assert rc == 1, err
    assert err.count("\n") == 1 and "Traceback" not in err and "internal error" not in err, err
    assert err.startswith(f"compd bench: pt100_1 at 127.0.0.1:{port}")
    if listening:
        assert "did not answer a read of holding register 0 (unit 1) within 0.5 s" in err, err
    else:
        assert "no connection within 0.5 s (nothing listens there)" in err, err
    assert "python -m hil_sim serve" in err
    assert took_s < 60, took_s  # the loops never ran against the silent devices


def test_naive_loop_names_the_device_that_stops_answering(tmp_path):
    """A device that stops answering during the run: the naive loop's request, named, not pymodbus's exception."""
    model = tmp_path / "m.yaml"
    model.write_text("kind: mlr\ninputs: [T1]\noutputs: [x1]\nparams: {coef_um_per_k: [[1.0]], intercept_um: [0.0]}\n")
    with silent_device() as port, pytest.raises(bench.DeviceSilent) as e:
        bench.run_naive_loop(model, ["T1"], {"pt100_1": port, "pmc": port}, cycles=5, period_s=0.002)
    assert str(e.value) == (
        f"pt100_1 at 127.0.0.1:{port} did not answer the naive loop's read of holding register 0 (unit 1)"
        f" within {bench.NAIVE_RETRIES + 1} tries of {bench.NAIVE_TIMEOUT_S:g} s: the simulated devices"
        " (python -m hil_sim serve) stopped answering; is the PC too loaded to serve them?"
    )

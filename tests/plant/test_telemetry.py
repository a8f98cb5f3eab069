"""Sparkplug B telemetry against a real mosquitto: births, aliases, data by exception, events.

Also TLS and passwords, store and forward.
"""

from __future__ import annotations

import copy
import errno
import math
import os
import time
from pathlib import Path
from typing import Any

import pytest

from compd.cycle.statusblock import signal_unit
from compd.plant.buffer import StoreAndForward
from compd.plant.sparkplug import (
    UNALIASED,
    AliasResolver,
    DataType,
    MetricDef,
    PayloadMessage,
    encode,
    topic,
)
from compd.plant.spec import TelemetrySpec
from compd.plant.telemetry import (
    DEADBAND_BY_UNIT,
    DEVICE_COMMANDS,
    EVENT_METRICS,
    Telemetry,
    device_metrics,
    moved,
)
from compd.service.status import render

from .broker import Listener, Message, Mosquitto, Tls, metric


def snapshot(i: int) -> dict[str, Any]:
    """A status snapshot of a two-axis machine, its values moving with `i`."""
    return {
        "state": "running",
        "observe": False,
        "word": f"0x{(0x4000 + i) & 0xFFFF:04X}",
        "axes": {
            "x": {
                "correction_um": -0.5 * i,
                "target_um": -0.5 * i,
                "prediction_um": 0.5 * i,
                "enable": True,
                "state": "normal",
            },
            "z": {
                "correction_um": 1.0,
                "target_um": float("nan"),
                "prediction_um": None,
                "enable": False,
                "state": "fault",
            },
        },
        "signals": {
            "T_xi": {"value": 20.0 + 0.01 * i, "quality": "good"},
            "speed_rpm": {"value": None, "quality": "comms_lost"},
        },
        "loop": {
            "period_ms": 2.0,
            "cycles": 1000 * i,
            "misses": 0,
            "lateness_us": {"p99": 12.5, "max": 80.0},
            "cycle_compute_us": {"p99": 90.0},
        },
        "model": {"kind": "lvr", "file": "/m.yaml", "fit": {"fitted_at": "2026-11-01T08:00:00Z"}},
    }


def noisy(i: int) -> dict[str, Any]:
    """A snapshot whose values move as a machine's do: float noise under the deadbands, real steps
    over them, a null that comes and goes, a state and a flag that flip now and then."""
    snap = snapshot(i)
    x, z = snap["axes"]["x"], snap["axes"]["z"]
    wobble = (i * 7) % 3 - 1  # -1, 0, 1: noise
    x["prediction_um"] = 0.5 * (i // 15) + 0.004 * wobble  # a 0.5 µm step every 15 samples, noise of ±0.004 µm
    x["correction_um"] = x["target_um"] = -x["prediction_um"]
    z["target_um"] = float("nan") if (i // 13) % 2 else 1.0  # null, then a number, then null ...
    z["state"] = "fault" if (i // 7) % 2 else "normal"
    z["enable"] = z["state"] == "normal"
    snap["word"] = f"0x{0x4000 + i // 4:04X}"
    snap["signals"]["T_xi"]["value"] = 20.0 + 0.01 * (i // 5) + 0.002 * wobble  # 0.01 °C steps, 0.002 °C noise
    snap["loop"]["lateness_us"]["max"] = 80.0 + 0.2 * wobble  # 0.4 µs from top to bottom: under the 0.5 µs deadband
    return snap


def spec(tmp_path: Path, port: int, **kw: Any) -> TelemetrySpec:
    base = dict(
        host="127.0.0.1",
        port=port,
        client_id="t-edge1",
        group_id="plant",
        edge_node_id="edge1",
        device_id="m1",
        buffer_path=tmp_path / "buf.sqlite",
        buffer_max_bytes=10_000_000,
        period_s=0.1,
        keepalive_s=5,
        reconnect_max_s=1.0,
        properties={"config": "/c.yaml"},
        slack_s=0.0,
    )
    base.update(kw)
    return TelemetrySpec(**base)


def feed(tel: Telemetry, first: int, n: int, t0_s: float, period_s: float = 0.1, make: Any = snapshot) -> None:
    """n samples (`make(i)`), a period apart on the sample clock (the wall clock is not waited for)."""
    for i in range(first, first + n):
        assert tel.sample(make(i), t_unix_s=t0_s + i * period_s)


def named(*listeners: Listener) -> list[Message]:
    """The listeners' messages in arrival order, one listener after the other (copies), the
    metrics that came by alias named from the births before them, as a Sparkplug host does
    (compd.plant.sparkplug.AliasResolver); every alias of an NDATA or DDATA must have been
    declared by the birth of its node or device."""
    msgs: list[Message] = []
    for listener in listeners:
        with listener._lock:
            msgs += copy.deepcopy(listener.messages)
    resolver = AliasResolver()
    for m in msgs:
        unknown = resolver.resolve(m.topic, m.payload)
        assert not unknown or m.kind.endswith("CMD"), f"{m.topic}: aliases {unknown} that no birth declared"
    return msgs


def of(listener: Listener, kind: str) -> list[Message]:
    """The messages of one kind, named (`named`)."""
    return [m for m in named(listener) if m.kind == kind]


def truth(i: int, n: int, snap: Any = None) -> dict[str, Any]:
    """The device's metrics of sample number `n`, taken from snapshot(i) (or `snap`): what a full
    refresh carries."""
    return {"Sample": n, **{d.name: v for d, v in device_metrics(snapshot(i) if snap is None else snap)}}


def units(births: list[Message]) -> dict[str, str | None]:
    return {x.name: x.properties.get("engUnit") for b in births for x in b.payload.metrics}


def same(unit: str | None, held: Any, true: Any) -> bool:
    """Whether a host's value is the true one: a number within its unit's deadband, anything else equal."""
    if isinstance(true, float) and isinstance(held, float):
        return abs(held - true) <= DEADBAND_BY_UNIT.get(unit or "", 0.0) + 1e-9
    return held == true and (held is None) == (true is None)


def states(msgs: list[Message]) -> list[tuple[int, dict[str, Any], bool]]:
    """Per DDATA sample in arrival order: (Sample, the device's state a historian holds after it —
    the DBIRTH's values, then every DDATA's on top —, whether the sample came whole)."""
    state: dict[str, Any] = {}
    born: set[str] = set()
    out = []
    for m in msgs:
        if m.kind == "DBIRTH":
            state = {x.name: x.value for x in m.payload.metrics}
            born = set(state) - {e.name for e in EVENT_METRICS} - {d.name for d in DEVICE_COMMANDS}
        elif m.kind == "DDATA" and any(x.name == "Sample" for x in m.payload.metrics):
            got = {x.name: x.value for x in m.payload.metrics}
            state.update(got)
            out.append((got["Sample"], dict(state), set(got) >= born))
    return out


def samples(listener: Listener) -> list[tuple[int, bool]]:
    """(Sample number, historical) of every DDATA sample received, in arrival order."""
    out = []
    for m in of(listener, "DDATA"):
        try:
            s = metric(m.payload, "Sample")
        except KeyError:
            continue  # an event
        out.append((s.value, s.is_historical))
    return out


def test_signal_units_from_names() -> None:
    assert signal_unit("err_z_um") == "µm"
    assert signal_unit("T_xi") == "°C"
    assert signal_unit("speed_rpm") == "rpm"
    assert signal_unit("load") is None


def test_device_metrics_of_a_snapshot() -> None:
    m = {d.name: (d, v) for d, v in device_metrics(snapshot(4))}
    assert m["Word"] == (MetricDef("Word", DataType.UInt16), 0x4004)
    assert m["Axis/x/correction_um"] == (MetricDef("Axis/x/correction_um", DataType.Double, "µm"), -2.0)
    assert m["Axis/z/target_um"][1] is None  # NaN: null, not a number that is not one
    assert m["Signal/speed_rpm/value"][1] is None and m["Signal/speed_rpm/quality"][1] == "comms_lost"
    assert m["Signal/T_xi/value"][0].unit == "°C"
    assert m["Loop/cycles"] == (MetricDef("Loop/cycles", DataType.UInt64), 4000)
    assert m["Model/fitted_at"][1] == "2026-11-01T08:00:00Z"
    # a snapshot without loop or model (a replayed log): those metrics are left out, nothing fails
    assert "Loop/cycles" not in {d.name for d, _ in device_metrics({"axes": {}, "signals": {}})}


def test_a_stale_cycle_s_metrics_say_so() -> None:
    """The same metrics (no rebirth): State and each axis's state `stale`, enable null (not confirmed)."""
    from compd.service.status import mark_stale

    snap = snapshot(4)
    mark_stale(snap)
    m = {d.name: v for d, v in device_metrics(snap)}
    assert m["State"] == "stale" and m["Axis/x/state"] == "stale" and m["Axis/z/state"] == "stale"
    assert m["Axis/x/enable"] is None and m["Axis/x/correction_um"] == -2.0  # the last value, said stale
    assert [d for d, _ in device_metrics(snap)] == [d for d, _ in device_metrics(snapshot(4))]


def test_births_data_and_events(tmp_path: Path) -> None:
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 1, t0)  # the first sample: the births can go out
            listener.wait_for(lambda: listener.of("DBIRTH"))
            feed(tel, 1, 19, t0)
            tel.event("axis_fault", "z", "input T_xi bad")
            listener.wait_for(lambda: len(samples(listener)) >= 20 and len(listener.of("DDATA")) >= 21)
        finally:
            final = tel.stop()
            listener.stop()
        nbirth, dbirth = listener.of("NBIRTH"), listener.of("DBIRTH")
        assert len(nbirth) == 1 and len(dbirth) == 1
        assert nbirth[0].topic == "spBv1.0/plant/NBIRTH/edge1"
        assert dbirth[0].topic == "spBv1.0/plant/DBIRTH/edge1/m1"
        nb = nbirth[0].payload
        assert nb.seq == 0 and metric(nb, "bdSeq").datatype == DataType.UInt64
        assert metric(nb, "Properties/config").value == "/c.yaml"
        db = dbirth[0].payload
        assert db.seq == 1
        names = {m.name for m in db.metrics}
        events = {"Event/kind", "Event/subject", "Event/reason"}
        # every metric is born: the samples', the events' and the one a DCMD may write
        assert {d.name for d, _ in device_metrics(snapshot(0))} | {"Sample", "Model/apply"} | events == names
        assert all(metric(db, n).is_null for n in events) and all(m.timestamp_ms == db.timestamp_ms for m in db.metrics)
        assert metric(db, "Axis/x/correction_um").properties.get("engUnit") == "µm"
        assert metric(db, "Axis/x/correction_um").datatype == DataType.Double
        # name and alias on every birth metric (but Node Control/Rebirth: by name only), each alias
        # once across the node and its device
        born = [*nb.metrics, *db.metrics]
        assert [m.name for m in born if m.alias is None] == ["Node Control/Rebirth"] == sorted(UNALIASED)
        aliases = [m.alias for m in born if m.alias is not None]
        assert len(set(aliases)) == len(aliases) and min(aliases) >= 1
        nums = samples(listener)
        assert [n for n, _ in nums] == list(range(1, 21))  # every sample, in order, once
        assert not any(h for n, h in nums if n > 1)  # live (the first was taken before the connection)
        # by alias (the conformance test checks on the bytes that no name goes with it); the
        # datatype stays (Tahu's decoder needs it)
        assert all(
            x.alias is not None and x.datatype is not DataType.Unknown
            for m in listener.of("DDATA")
            for x in m.payload.metrics
        )
        data = of(listener, "DDATA")
        assert [m.payload.seq for m in data] == list(range(2, 2 + len(data)))  # seq runs on after the births
        s5 = next(m.payload for m in data if metric(m.payload, "Sample").value == 6)
        assert metric(s5, "Axis/x/correction_um").value == -2.5
        assert s5.timestamp_ms == int((t0 + 5 * 0.1) * 1000)
        assert all(x.timestamp_ms == s5.timestamp_ms for x in s5.metrics)
        # by exception: the first sample after the births whole, then what changed (with Sample)
        first = next(m.payload for m in data if metric(m.payload, "Sample").value == 1)
        assert {x.name for x in first.metrics} == {d.name for d, _ in device_metrics(snapshot(0))} | {"Sample"}
        assert metric(first, "Axis/z/target_um").is_null
        assert {x.name for x in s5.metrics} == {
            "Sample",
            "Word",
            "Axis/x/correction_um",
            "Axis/x/target_um",
            "Axis/x/prediction_um",
            "Signal/T_xi/value",
            "Loop/cycles",
        }
        # ... and what a host holds is every sample whole
        u = units(dbirth)
        for n, state, _ in states(named(listener)):
            want = truth(n - 1, n)
            assert all(same(u.get(k), state[k], v) for k, v in want.items()), (n, state, want)
        ev = [m.payload for m in data if any(x.name == "Event/kind" for x in m.payload.metrics)]
        assert [(metric(e, "Event/kind").value, metric(e, "Event/subject").value) for e in ev] == [("axis_fault", "z")]
        assert {x.name for x in ev[0].metrics} == events  # an event goes whole
        death = listener.of("NDEATH")
        assert len(death) == 1 and metric(death[0].payload, "bdSeq").value == metric(nb, "bdSeq").value
        assert final["buffered"] == 0 and final["dropped"] == 0
        assert not listener.errors


def test_broker_outage_every_sample_in_order_once(tmp_path: Path) -> None:
    """The broker killed mid-run (5 s here; 60 s in make accept): the samples taken meanwhile
    wait on disk and arrive, marked historical, in order, none twice."""
    broker = Mosquitto(tmp_path / "broker").start()
    listener = Listener(broker.port, host_id="historian")
    tel = Telemetry(spec(tmp_path, broker.port, primary_host_id="historian"))
    try:
        tel.start()
        t0 = time.time()
        feed(tel, 0, 30, t0)
        listener.wait_for(lambda: len(samples(listener)) >= 30)
        broker.kill()
        for i in range(30, 80):  # samples on the wall clock's pace: some while it is down
            tel.sample(snapshot(i), t_unix_s=t0 + i * 0.1)
            time.sleep(0.1)
        assert tel.get_status()["connected"] is False
        assert tel.get_status()["buffered"] > 0
        broker.start()
        # no race with the listener's return: compd waits for this primary host's STATE, which
        # the listener publishes once it has subscribed again
        listener.wait_for(lambda: len(listener.of("NBIRTH")) >= 2, timeout_s=60)
        feed(tel, 80, 20, t0)
        listener.wait_for(lambda: len({n for n, _ in samples(listener)}) >= 100, timeout_s=60)
    finally:
        tel.stop()
        listener.stop()
        broker.kill()
    nums = samples(listener)
    numbers = [n for n, _ in nums]
    assert numbers == list(range(1, 101)), numbers  # all, in order, none twice
    hist = [n for n, h in nums if h]
    assert set(range(45, 75)) <= set(hist)  # what waited is marked historical ...
    assert not any(h for n, h in nums if n > 80)  # ... and what was taken after the return is not
    assert len(listener.of("NBIRTH")) == 2  # a new birth on the return, with a new bdSeq
    b1, b2 = (metric(m.payload, "bdSeq").value for m in listener.of("NBIRTH"))
    assert b2 == (b1 + 1) % 256


def test_tls_client_certificate_and_password(tmp_path: Path) -> None:
    tls = Tls(tmp_path / "pki")
    with Mosquitto(
        tmp_path / "broker", users={"edge1": "s3cret", "host": "h0st"}, tls=tls, require_certificate=True
    ) as broker:
        listener = Listener(broker.port, username="host", password="h0st", tls=tls)
        wrong = Telemetry(
            spec(
                tmp_path / "w",
                broker.port,
                username="edge1",
                password="wrong",
                ca_file=str(tls.ca),
                cert_file=str(tls.client_cert),
                key_file=str(tls.client_key),
                client_id="w",
            )
        )
        good = Telemetry(
            spec(
                tmp_path / "g",
                broker.port,
                username="edge1",
                password="s3cret",
                ca_file=str(tls.ca),
                cert_file=str(tls.client_cert),
                key_file=str(tls.client_key),
            )
        )
        (tmp_path / "w").mkdir()
        (tmp_path / "g").mkdir()
        try:
            wrong.start()
            good.start()
            t0 = time.time()
            feed(wrong, 0, 3, t0)
            feed(good, 0, 5, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 5)
            deadline = time.monotonic() + 20
            while wrong.get_status()["last_error"] is None and time.monotonic() < deadline:
                time.sleep(0.05)
            st = wrong.get_status()
            assert st["connected"] is False and st["buffered"] == 3  # kept, not lost
            assert "not authorized" in st["last_error"].lower() or "bad user" in st["last_error"].lower()
        finally:
            good.stop()
            wrong.stop()
            listener.stop()
    assert [n for n, _ in samples(listener)] == [1, 2, 3, 4, 5]
    assert {m.topic.split("/")[3] for m in listener.messages} == {"edge1"}


def test_a_full_buffer_drops_the_oldest_and_says_so(tmp_path: Path) -> None:
    port = 1  # nothing listens: every sample waits
    body = len(str(snapshot(0)))  # about a sample's size
    tel = Telemetry(spec(tmp_path, port, buffer_max_bytes=20 * body, reconnect_max_s=60))
    tel.start()
    try:
        feed(tel, 0, 200, time.time())
        deadline = time.monotonic() + 20
        while tel.get_status()["dropped"] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        st = tel.stop()
    assert st["dropped"] > 100 and 0 < st["buffered"] < 100
    assert st["buffered"] + st["dropped"] == 200  # every sample is either kept or counted
    buf = StoreAndForward(tmp_path / "buf.sqlite", 20 * body)
    try:
        kept = buf.pending(1000)
        assert kept[-1].body.startswith(b'[["Sample", 200]')  # the newest is kept
    finally:
        buf.close()


def test_rebirth_and_a_command_that_is_not_sparkplug(tmp_path: Path) -> None:
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port))
        try:
            tel.start()
            feed(tel, 0, 3, time.time())
            listener.wait_for(lambda: len(samples(listener)) >= 3)
            cmd = topic("plant", "NCMD", "edge1")
            listener.client.publish(cmd, b"\xff\x00garbage", qos=1)
            listener.client.publish(
                cmd,
                encode([(MetricDef("Node Control/Rebirth", DataType.Boolean), True)], timestamp_ms=0, seq=None),
                qos=1,
            )
            listener.wait_for(lambda: len(listener.of("DBIRTH")) >= 2)
            listener.client.publish(
                topic("plant", "NCMD", "edge1"),
                encode([(MetricDef("Node Control/Model", DataType.String), "kind: lvr")], timestamp_ms=0, seq=None),
                qos=1,
            )
            listener.wait_for(
                lambda: any(
                    any(
                        x.name == "Model/result" and "takes no remote models" in (x.value or "")
                        for x in m.payload.metrics
                    )
                    for m in of(listener, "NDATA")
                )
            )
        finally:
            tel.stop()
            listener.stop()
    assert tel.commands_seen == 3
    results = [x.value for m in of(listener, "NDATA") for x in m.payload.metrics if x.name == "Model/result"]
    assert any("not a Sparkplug B payload" in r for r in results)


def test_a_buffer_set_aside_never_restarts_sample_or_bdseq(tmp_path: Path) -> None:
    """A historian keys on `Sample`: after the buffer file is found corrupt and set aside, the
    numbers go on from the counters file beside it (never 1 again), and so does bdSeq."""

    def session(first: int, n: int) -> tuple[list[int], int]:
        with Mosquitto(tmp_path / "broker") as broker:
            listener = Listener(broker.port)
            tel = Telemetry(spec(tmp_path, broker.port))
            try:
                tel.start()
                feed(tel, first, n, time.time())
                listener.wait_for(lambda: len(samples(listener)) >= n)
            finally:
                tel.stop()
                listener.stop()
            return [s for s, _ in samples(listener)], metric(listener.of("NBIRTH")[0].payload, "bdSeq").value

    first, bd1 = session(0, 5)
    assert first == [1, 2, 3, 4, 5]
    buf = tmp_path / "buf.sqlite"
    for side in (buf, buf.with_name(buf.name + "-wal"), buf.with_name(buf.name + "-shm")):
        if side.exists():
            side.unlink()
    buf.write_bytes(b"this is not an SQLite database" * 100)  # the buffer, corrupt
    second, bd2 = session(5, 3)
    assert second == [6, 7, 8] and bd2 == (bd1 + 1) % 256
    assert [p for p in tmp_path.iterdir() if p.name.startswith("buf.sqlite.corrupt-")]  # kept, not deleted
    assert (tmp_path / "buf.sqlite.counters").exists()


def test_a_full_disk_under_the_buffer_is_said_once_and_telemetry_goes_on_live(tmp_path: Path, caplog: Any) -> None:
    """SQLite's `database or disk is full` from the buffer (what a full disk gives; the real one below)
    stops nothing: the telemetry says so once, keeps its connection and publishes live from memory,
    and buffers on disk again when the file can be written."""
    import logging
    import sqlite3

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port, reconnect_max_s=0.5))
        real_init = StoreAndForward.__init__
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 3, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 3)
            buf = tel.buffer
            assert buf is not None

            def full(*a: Any, **k: Any) -> Any:
                raise sqlite3.OperationalError("database or disk is full")

            buf.put = buf.set_meta = full  # the disk fills up: this file, and any opened again
            StoreAndForward.__init__ = full  # type: ignore[method-assign]
            feed(tel, 3, 5, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 8)  # live, on the same connection
            st = tel.get_status()
            assert st["connected"] and st["buffer"] == "memory" and "disk is full" in st["buffer_error"]
            assert tel.connects == 1 and st["dropped"] == 0
            StoreAndForward.__init__ = real_init  # type: ignore[method-assign]  # room again
            listener.wait_for(lambda: tel.get_status()["buffer"] == "disk")
            feed(tel, 8, 4, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 12)
        finally:
            StoreAndForward.__init__ = real_init  # type: ignore[method-assign]
            tel.stop()
            listener.stop()
        numbers = [s for s, _ in samples(listener)]
        assert sorted(set(numbers)) == list(range(1, 13))  # every sample, none lost
        said = [r for r in caplog.records if getattr(r, "event", None) == "telemetry_unbuffered"]
        assert len(said) == 1 and said[0].levelname == "ERROR" and "disk is full" in said[0].reason
        assert [r.event for r in caplog.records if getattr(r, "event", None) == "telemetry_buffered"] == [
            "telemetry_buffered"
        ]
        assert not [r for r in caplog.records if getattr(r, "event", None) == "telemetry_error"]


class SmallDisk:
    """A tmpfs of `size_kb` mounted at `path` (root: CI runs as root), filled up and freed again by a file
    of its own: the buffer's SQLite meets a real ENOSPC ("database or disk is full")."""

    def __init__(self, path: Path, size_kb: int = 512) -> None:
        import shutil
        import subprocess

        if os.geteuid() != 0 or shutil.which("mount") is None:
            pytest.skip("a disk that fills needs root to mount a tmpfs")
        path.mkdir()
        run = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k,mode=0700", "tmpfs", str(path)],
            capture_output=True,
            text=True,
        )
        if run.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {run.stderr.strip()}")
        self.path = path
        self.filler = path / "filler"

    def fill(self) -> None:
        fd = os.open(self.filler, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            while True:
                os.write(fd, b"\0" * 4096)
        except OSError as e:
            assert e.errno == errno.ENOSPC, e
        finally:
            os.close(fd)

    def free(self) -> None:
        self.filler.unlink()

    def __enter__(self) -> SmallDisk:
        return self

    def __exit__(self, *exc: object) -> None:
        import subprocess

        subprocess.run(["umount", str(self.path)], check=True)


def test_telemetry_on_a_disk_that_fills_publishes_live_and_buffers_again_when_it_has_room(
    tmp_path: Path, caplog: Any
) -> None:
    """Issue 39 item 7: the buffer's disk filled, the telemetry never reconnected. Now it says so once,
    stays connected and publishes every sample live; freed, the disk buffers again."""
    import logging

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with SmallDisk(tmp_path / "disk") as disk, Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(disk.path, broker.port, reconnect_max_s=0.5))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 3, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 3)
            assert tel.get_status().get("buffer_error") is None
            disk.fill()
            feed(tel, 3, 20, t0)  # each a frame more of the buffer's WAL at least: the first meets the full disk
            n = 23
            listener.wait_for(lambda: {s for s, _ in samples(listener)} >= set(range(1, n + 1)))  # all, live
            st = tel.get_status()
            assert st["buffer"] == "memory", st
            assert st["connected"] and tel.connects == 1, st  # never dropped its connection
            assert "disk is full" in st["buffer_error"] and st["dropped"] == 0
            assert "BUFFER IN MEMORY (" in render({"telemetry": st}, True, "running")  # compd status says so
            disk.free()
            listener.wait_for(lambda: tel.get_status()["buffer"] == "disk")
            assert tel.disk is not None
            before = tel.disk.last_id
            feed(tel, n, 5, t0)
            n += 5
            listener.wait_for(lambda: len({s for s, _ in samples(listener)}) >= n)
            assert tel.disk.last_id >= before + 5  # on disk again: buffered before it is sent
        finally:
            tel.stop()
            listener.stop()
        assert sorted({s for s, _ in samples(listener)}) == list(range(1, n + 1))  # none lost
        events = [r.event for r in caplog.records if getattr(r, "event", "").startswith("telemetry_")]
        assert events.count("telemetry_unbuffered") == 1 and events.count("telemetry_buffered") == 1, events
        assert "telemetry_error" not in events and "telemetry_down" not in events


def test_telemetry_that_starts_on_a_full_disk_runs_live_and_buffers_once_it_has_room(
    tmp_path: Path, caplog: Any
) -> None:
    """Issue 39 item 7: a service that started on a full disk had no telemetry for good."""
    import logging

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with SmallDisk(tmp_path / "disk") as disk, Mosquitto(tmp_path / "broker") as broker:
        disk.fill()
        listener = Listener(broker.port)
        tel = Telemetry(spec(disk.path, broker.port, reconnect_max_s=0.5))
        try:
            tel.start()  # it did raise: "telemetry off"
            st = tel.get_status()
            assert st["buffer"] == "memory" and "disk is full" in st["buffer_error"]
            t0 = time.time()
            feed(tel, 0, 5, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 5)
            assert tel.get_status()["connected"]
            disk.free()
            listener.wait_for(lambda: tel.get_status()["buffer"] == "disk")
            feed(tel, 5, 5, t0)
            listener.wait_for(lambda: len({s for s, _ in samples(listener)}) >= 10)
        finally:
            tel.stop()
            listener.stop()
        assert sorted({s for s, _ in samples(listener)}) == list(range(1, 11))
        said = [r for r in caplog.records if getattr(r, "event", None) == "telemetry_unbuffered"]
        assert len(said) == 1 and "disk is full" in said[0].reason


def test_a_command_with_thousands_of_metrics_is_one_rebirth_and_one_line(tmp_path: Path, caplog: Any) -> None:
    import logging

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port))
        try:
            tel.start()
            feed(tel, 0, 2, time.time())
            listener.wait_for(lambda: len(samples(listener)) >= 2)
            flood = [(MetricDef("Node Control/Rebirth", DataType.Boolean), True)] * 6_000
            flood += [(MetricDef(f"junk/{i}", DataType.Int32), i) for i in range(3_000)]  # within decode's 10 000
            listener.client.publish(topic("plant", "NCMD", "edge1"), encode(flood, timestamp_ms=0, seq=None), qos=1)
            listener.wait_for(lambda: len(listener.of("DBIRTH")) >= 2 and tel.commands_seen == 1)
        finally:
            tel.stop()
            listener.stop()
    assert len(listener.of("DBIRTH")) == 2  # one rebirth for the one command
    events = [getattr(r, "event", None) for r in caplog.records]
    assert events.count("telemetry_rebirth") == 1 and events.count("telemetry_command_bad") == 1
    bad = next(r for r in caplog.records if getattr(r, "event", None) == "telemetry_command_bad")
    assert "3000" in bad.reason


def test_what_is_news_by_datatype_and_unit() -> None:
    um = MetricDef("Axis/x/correction_um", DataType.Double, "µm")
    deg = MetricDef("Signal/T_xi/value", DataType.Double, "°C")
    bare = MetricDef("Signal/load/value", DataType.Double)
    assert moved(um, 1.0)  # nothing sent yet
    assert not moved(um, 1.0 + 0.009, 1.0) and moved(um, 1.0 + 0.011, 1.0)
    assert not moved(deg, 20.004, 20.0) and moved(deg, 20.01, 20.0)  # a 0.01 °C step is always news
    assert moved(bare, 1.0 + 1e-12, 1.0)  # no unit, no deadband
    assert moved(um, None, 1.0) and moved(um, 1.0, None) and not moved(um, None, None)
    assert moved(MetricDef("Axis/x/state", DataType.String), "fault", "normal")
    assert not moved(MetricDef("Loop/cycles", DataType.UInt64), 7, 7) and moved(
        MetricDef("Word", DataType.UInt16), 1, 0
    )
    assert moved(MetricDef("Axis/x/enable", DataType.Boolean), None, False)
    assert not math.isnan(DEADBAND_BY_UNIT["µm"]) and all(v > 0 for v in DEADBAND_BY_UNIT.values())


def test_report_by_exception_with_deadbands_and_a_full_refresh(tmp_path: Path) -> None:
    """Noise under the deadbands is not sent, a step over them is; every sample time the full
    refresh is due, a whole sample; what a host holds is every sample within the deadbands."""
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port, full_refresh_s=1.0))  # 10 samples of 0.1 s
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 1, t0, make=noisy)
            listener.wait_for(lambda: listener.of("DBIRTH"))
            feed(tel, 1, 99, t0, make=noisy)
            listener.wait_for(lambda: len(samples(listener)) >= 100)
        finally:
            tel.stop()
            listener.stop()
    msgs = named(listener)
    u = units([m for m in msgs if m.kind == "DBIRTH"])
    held = states(msgs)
    assert [n for n, _, _ in held] == list(range(1, 101))
    for n, state, _ in held:
        want = truth(n - 1, n, noisy(n - 1))
        bad = {k: (state.get(k), v) for k, v in want.items() if not same(u.get(k), state.get(k), v)}
        assert not bad, (n, bad)
    whole = [n for n, _, full in held if full]
    assert whole == list(range(1, 101, 10)), whole  # the first, then every 1.0 s of sample time
    assert (tel.full_refreshes, tel.exceptions) == (10, 90)
    data = {metric(m.payload, "Sample").value: {x.name for x in m.payload.metrics} for m in msgs if m.kind == "DDATA"}
    # the noise (±0.004 µm, ±0.002 °C, ±0.2 µs) never goes out between the steps ...
    assert "Signal/T_xi/value" not in data[3] and "Axis/x/prediction_um" not in data[3]
    assert "Loop/lateness_max_us" not in set().union(*(data[n] for n in range(2, 101) if n not in whole))
    # ... the steps do (0.01 °C at i = 5, 0.5 µm at i = 15: samples 6 and 16), and every exact change
    assert "Signal/T_xi/value" in data[6] and "Axis/x/prediction_um" in data[16]
    assert {"Axis/z/state", "Axis/z/enable"} <= data[8] and "Axis/z/target_um" in data[14]
    assert all("Sample" in names for names in data.values())


def test_full_refresh_0_sends_every_sample_whole(tmp_path: Path) -> None:
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port, full_refresh_s=0.0))
        try:
            tel.start()
            feed(tel, 0, 12, time.time(), make=noisy)
            listener.wait_for(lambda: len(samples(listener)) >= 12)
        finally:
            tel.stop()
            listener.stop()
    assert [full for _, _, full in states(named(listener))] == [True] * 12
    assert tel.exceptions == 0


def test_samples_buffered_in_an_outage_replay_right_after_a_restart_with_other_aliases(tmp_path: Path) -> None:
    """A sample buffered during an outage is sent (after a restart whose metric set, and so
    whose aliases, changed) in the new births' aliases: a host reads every one as it was taken."""

    def with_new_signal(i: int) -> dict[str, Any]:
        snap = snapshot(i)
        snap["signals"] = {"A_bed_c": {"value": 19.5, "quality": "good"}, **snap["signals"]}  # sorts first
        return snap

    broker = Mosquitto(tmp_path / "broker").start()
    before = Listener(broker.port, client_id="before")
    try:
        tel = Telemetry(spec(tmp_path, broker.port, reconnect_max_s=60))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 10, t0)
            before.wait_for(lambda: len(samples(before)) >= 10)
            broker.kill()
            before.wait_for(lambda: not tel.get_status()["connected"])
            feed(tel, 10, 20, t0)  # into the buffer
            before.wait_for(lambda: tel.get_status()["buffered"] >= 20)
        finally:
            first = tel.stop(drain_s=0.0)
        assert first["buffered"] == 20
    finally:
        before.stop()
    broker.start()
    after = Listener(broker.port, client_id="after")  # a host that is there before compd returns
    try:
        tel = Telemetry(spec(tmp_path, broker.port))  # the daemon again, with a signal more
        try:
            tel.start()
            feed(tel, 30, 10, t0, make=with_new_signal)
            after.wait_for(lambda: len(samples(after)) >= 30, timeout_s=60)
        finally:
            tel.stop()
    finally:
        after.stop()
        broker.kill()
    msgs = named(before, after)
    births = [m for m in msgs if m.kind == "DBIRTH"]
    assert len(births) == 2
    alias = [{x.name: x.alias for x in b.payload.metrics} for b in births]
    assert alias[0]["Signal/T_xi/value"] != alias[1]["Signal/T_xi/value"]  # other aliases for the same metric
    held = states(msgs)
    assert [n for n, _, _ in held] == list(range(1, 41))  # every sample, in order, once
    hist = {
        metric(m.payload, "Sample").value
        for m in msgs
        if m.kind == "DDATA" and metric(m.payload, "Sample").is_historical
    }
    assert set(range(11, 31)) <= hist
    u = units(births)
    for n, state, _ in held:
        want = truth(n - 1, n, snapshot(n - 1) if n <= 30 else with_new_signal(n - 1))
        bad = {k: (state.get(k), v) for k, v in want.items() if not same(u.get(k), state.get(k), v)}
        assert not bad, (n, bad)
    assert tel.dropped_unknown == 0


def test_commands_by_alias(tmp_path: Path, caplog: Any) -> None:
    """A host that writes by alias (Sparkplug 3.0), without a datatype: the model metric of NCMD
    and of DCMD is understood; an alias no birth gave is ignored and said."""
    import logging

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port))
        try:
            tel.start()
            feed(tel, 0, 2, time.time())
            listener.wait_for(lambda: len(samples(listener)) >= 2)
            node = {x.name: x.alias for x in listener.of("NBIRTH")[0].payload.metrics}
            device = {x.name: x.alias for x in listener.of("DBIRTH")[0].payload.metrics}
            for kind, dev, alias in (("NCMD", None, node["Node Control/Model"]), ("DCMD", "m1", device["Model/apply"])):
                msg = PayloadMessage(timestamp=1)  # the same request twice: answered twice all the same
                msg.metrics.add(alias=alias, string_value="kind: lvr")  # by alias, no datatype
                listener.client.publish(topic("plant", kind, "edge1", dev), msg.SerializeToString(), qos=1)
            stray = PayloadMessage(timestamp=2)
            stray.metrics.add(alias=999_999, boolean_value=True)
            listener.client.publish(topic("plant", "NCMD", "edge1"), stray.SerializeToString(), qos=1)
            listener.wait_for(
                lambda: (
                    tel.commands_seen == 3
                    and len([x for m in of(listener, "NDATA") for x in m.payload.metrics if x.name == "Model/result"])
                    >= 2
                )
            )
        finally:
            tel.stop()
            listener.stop()
    results = [x.value for m in of(listener, "NDATA") for x in m.payload.metrics if x.name == "Model/result"]
    assert len(results) == 2 and all("takes no remote models" in r for r in results), results  # both understood
    bad = [r for r in caplog.records if getattr(r, "event", None) == "telemetry_command_bad"]
    assert len(bad) == 1 and "alias 999999" in bad[0].reason


def test_paho_never_holds_back_a_sample_of_the_window(tmp_path: Path) -> None:
    """paho queues a QoS 1 message beyond its in-flight limit and sends a QoS 0 one at once: an
    NDATA would overtake the samples it held back, seq out of order on the wire (seen in the
    conformance run). Its limit has room for the whole window and the NDEATH."""
    from compd.plant.telemetry import WINDOW

    client = Telemetry(spec(tmp_path, 1))._make_client()
    try:
        assert client._max_inflight_messages >= WINDOW + 1
    finally:
        client._reset_sockets()

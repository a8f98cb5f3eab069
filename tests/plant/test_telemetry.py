"""Sparkplug B telemetry against a real mosquitto: births, data, events, TLS and passwords, store and forward."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from compd.cycle.statusblock import signal_unit
from compd.plant.buffer import StoreAndForward
from compd.plant.sparkplug import DataType, MetricDef, encode, topic
from compd.plant.spec import TelemetrySpec
from compd.plant.telemetry import Telemetry, device_metrics

from .broker import Listener, Mosquitto, Tls, metric


def snapshot(i: int) -> dict[str, Any]:
    """A status snapshot of a two-axis machine, its values moving with `i`."""
    return {
        "state": "running", "observe": False, "word": f"0x{(0x4000 + i) & 0xFFFF:04X}",
        "axes": {"x": {"correction_um": -0.5 * i, "target_um": -0.5 * i, "prediction_um": 0.5 * i,
                       "enable": True, "state": "normal"},
                 "z": {"correction_um": 1.0, "target_um": float("nan"), "prediction_um": None,
                       "enable": False, "state": "fault"}},
        "signals": {"T_xi": {"value": 20.0 + 0.01 * i, "quality": "good"},
                    "speed_rpm": {"value": None, "quality": "comms_lost"}},
        "loop": {"period_ms": 2.0, "cycles": 1000 * i, "misses": 0,
                 "lateness_us": {"p99": 12.5, "max": 80.0}, "cycle_compute_us": {"p99": 90.0}},
        "model": {"kind": "lvr", "file": "/m.yaml", "fit": {"fitted_at": "2026-11-01T08:00:00Z"}},
    }


def spec(tmp_path: Path, port: int, **kw: Any) -> TelemetrySpec:
    base = dict(host="127.0.0.1", port=port, client_id="t-edge1", group_id="plant", edge_node_id="edge1",
                device_id="m1", buffer_path=tmp_path / "buf.sqlite", buffer_max_bytes=10_000_000,
                period_s=0.1, keepalive_s=5, reconnect_max_s=1.0, properties={"config": "/c.yaml"},
                slack_s=0.0)
    base.update(kw)
    return TelemetrySpec(**base)


def feed(tel: Telemetry, first: int, n: int, t0_s: float, period_s: float = 0.1) -> None:
    """n samples, a period apart on the sample clock (the wall clock is not waited for)."""
    for i in range(first, first + n):
        assert tel.sample(snapshot(i), t_unix_s=t0_s + i * period_s)


def samples(listener: Listener) -> list[tuple[int, bool]]:
    """(Sample number, historical) of every DDATA sample received, in arrival order."""
    out = []
    for m in listener.of("DDATA"):
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
        assert {d.name for d, _ in device_metrics(snapshot(0))} | {"Sample"} | events == names  # every metric is born
        assert all(metric(db, n).is_null for n in events) and all(m.timestamp_ms == db.timestamp_ms for m in db.metrics)
        assert metric(db, "Axis/x/correction_um").properties.get("engUnit") == "µm"
        assert metric(db, "Axis/x/correction_um").datatype == DataType.Double
        nums = samples(listener)
        assert [n for n, _ in nums] == list(range(1, 21))  # every sample, in order, once
        assert not any(h for n, h in nums if n > 1)  # live (the first was taken before the connection)
        data = listener.of("DDATA")
        assert [m.payload.seq for m in data] == list(range(2, 2 + len(data)))  # seq runs on after the births
        s5 = next(m.payload for m in data if metric(m.payload, "Sample").value == 6)
        assert metric(s5, "Axis/x/correction_um").value == -2.5
        assert metric(s5, "Axis/z/target_um").is_null
        assert s5.timestamp_ms == int((t0 + 5 * 0.1) * 1000)
        ev = [m.payload for m in data if any(x.name == "Event/kind" for x in m.payload.metrics)]
        assert [(metric(e, "Event/kind").value, metric(e, "Event/subject").value) for e in ev] == [("axis_fault", "z")]
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
        listener.resubscribed()
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
    with Mosquitto(tmp_path / "broker", users={"edge1": "s3cret", "host": "h0st"}, tls=tls,
                   require_certificate=True) as broker:
        listener = Listener(broker.port, username="host", password="h0st", tls=tls)
        wrong = Telemetry(spec(tmp_path / "w", broker.port, username="edge1", password="wrong", ca_file=str(tls.ca),
                               cert_file=str(tls.client_cert), key_file=str(tls.client_key), client_id="w"))
        good = Telemetry(spec(tmp_path / "g", broker.port, username="edge1", password="s3cret", ca_file=str(tls.ca),
                              cert_file=str(tls.client_cert), key_file=str(tls.client_key)))
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
            listener.client.publish(cmd, encode([(MetricDef("Node Control/Rebirth", DataType.Boolean), True)],
                                                timestamp_ms=0, seq=None), qos=1)
            listener.wait_for(lambda: len(listener.of("DBIRTH")) >= 2)
            listener.client.publish(topic("plant", "NCMD", "edge1"), encode(
                [(MetricDef("Node Control/Model", DataType.String), "kind: lvr")], timestamp_ms=0, seq=None), qos=1)
            listener.wait_for(lambda: any(
                any(x.name == "Model/result" and "takes no remote models" in (x.value or "") for x in m.payload.metrics)
                for m in listener.of("NDATA")))
        finally:
            tel.stop()
            listener.stop()
    assert tel.commands_seen == 3
    results = [x.value for m in listener.of("NDATA") for x in m.payload.metrics if x.name == "Model/result"]
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


def test_a_full_disk_under_the_buffer_is_said_once_and_telemetry_recovers(tmp_path: Path, caplog: Any) -> None:
    """SQLite's `database or disk is full` from the buffer (what a full disk gives) stops nothing
    for good: the telemetry says so once, drops the connection, and when the disk has room again
    it connects, is born again and sends the samples taken since."""
    import logging
    import sqlite3

    caplog.set_level(logging.INFO, logger="compd.telemetry")
    with Mosquitto(tmp_path / "broker") as broker:
        listener = Listener(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port, reconnect_max_s=0.5))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 3, t0)
            listener.wait_for(lambda: len(samples(listener)) >= 3)
            buf = tel.buffer
            real_put, real_set = buf.put, buf.set_meta

            def full(*a: Any, **k: Any) -> Any:
                raise sqlite3.OperationalError("database or disk is full")

            buf.put = buf.set_meta = full  # the disk fills up
            feed(tel, 3, 5, t0)
            listener.wait_for(lambda: tel.failures >= 3)
            st = tel.get_status()
            assert not st["connected"] and "disk is full" in st["last_error"] and st["dropped"] >= 1  # counted
            buf.put, buf.set_meta = real_put, real_set  # room again
            feed(tel, 8, 4, t0)
            listener.wait_for(lambda: tel.get_status()["connected"] and len(samples(listener)) >= 7)
        finally:
            tel.stop()
            listener.stop()
        numbers = [s for s, _ in samples(listener)]
        assert numbers[:3] == [1, 2, 3] and numbers[-1] > 3  # sent again after the disk had room
        assert len(listener.of("NBIRTH")) >= 2  # born again on the new connection
        said = [r for r in caplog.records if getattr(r, "event", None) == "telemetry_error"]
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

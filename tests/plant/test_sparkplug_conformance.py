"""Sparkplug B 3.0 rules, checked on every message compd publishes to a real mosquitto, decoded by Eclipse Tahu's payload library (npm, unpacked into build/ by the Makefile), not by compd's code: topics, births before data, bdSeq, seq, time stamps, every DDATA metric declared in DBIRTH with its type."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt

from compd.plant.sparkplug import DataType, MetricDef, encode
from compd.plant.telemetry import Telemetry
from tests.conftest import ROOT

from .broker import Mosquitto
from .test_telemetry import feed, spec

TAHU = ROOT / "build" / "tools" / "node" / "node_modules"
DECODER = Path(__file__).with_name("tahu_decode.js")
TYPES = {"NBIRTH", "NDEATH", "NDATA", "NCMD", "DBIRTH", "DDEATH", "DDATA", "DCMD"}
SAMPLES = 600  # more messages in each half than seq has values: it wraps


class Raw:
    """A subscriber to spBv1.0/# that keeps every message's topic and bytes, in arrival order."""

    def __init__(self, port: int) -> None:
        self.messages: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self._ready = threading.Event()
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="conformance", clean_session=True)
        c.on_connect = lambda cl, u, f, rc, p: cl.subscribe("spBv1.0/#", qos=1)
        c.on_subscribe = lambda *a: self._ready.set()
        c.on_message = self._on_message
        c.connect("127.0.0.1", port, keepalive=10)
        c.loop_start()
        self.client = c
        assert self._ready.wait(20), "the subscriber did not subscribe"

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        with self._lock:
            self.messages.append((msg.topic, bytes(msg.payload)))

    def count(self, kind: str) -> int:
        with self._lock:
            return sum(1 for t, _ in self.messages if t.split("/")[2] == kind)

    def stop(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
        self.client._reset_sockets()  # paho's wake-up socket pair, else closed only by the garbage collector


def _wait(cond: Any, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _tahu(messages: list[tuple[str, bytes]]) -> list[dict[str, Any]]:
    node = shutil.which("node")
    assert node, "no node: Node.js runs Eclipse Tahu's decoder"
    assert (TAHU / "sparkplug-payload").is_dir(), "no Tahu: `make build/tools/node/node_modules/sparkplug-payload/package.json`"
    lines = "".join(json.dumps({"topic": t, "hex": b.hex()}) + "\n" for t, b in messages)
    r = subprocess.run([node, str(DECODER)], input=lines, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "NODE_PATH": str(TAHU)})
    assert r.returncode == 0, r.stderr
    out = [json.loads(ln) for ln in r.stdout.splitlines()]
    assert len(out) == len(messages) and not [o for o in out if "error" in o], [o for o in out if "error" in o][:3]
    return out


def test_every_message_of_a_session_keeps_the_sparkplug_rules(tmp_path: Path) -> None:
    with Mosquitto(tmp_path / "broker") as broker:
        raw = Raw(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 1, t0)
            _wait(lambda: raw.count("DBIRTH") == 1, "the births")
            feed(tel, 1, SAMPLES // 2, t0)
            tel.event("axis_fault", "z", "input T_xi bad")
            _wait(lambda: raw.count("DDATA") >= SAMPLES // 2 + 1, "the first half")
            # a host asks for a rebirth: births again in the same session (same bdSeq, seq from 0)
            cmd = encode([(MetricDef("Node Control/Rebirth", DataType.Boolean), True)],
                         timestamp_ms=int(time.time() * 1000), seq=None)
            raw.client.publish("spBv1.0/plant/NCMD/edge1", cmd, qos=0)
            _wait(lambda: raw.count("DBIRTH") == 2, "the rebirth")
            feed(tel, SAMPLES // 2 + 1, SAMPLES - SAMPLES // 2 - 1, t0)
            _wait(lambda: raw.count("DDATA") >= SAMPLES + 1, "every sample")
        finally:
            tel.stop()
            _wait(lambda: raw.count("NDEATH") == 1, "the death certificate")
            raw.stop()
        decoded = _tahu([(t, b) for t, b in raw.messages if t.split("/")[2] != "NCMD"])
    checked = _check_rules(decoded)
    print(f"Sparkplug B 3.0 rules checked on {len(decoded)} messages decoded by Eclipse Tahu sparkplug-payload"
          f" 1.0.3: {', '.join(f'{k} {v}' for k, v in checked.items())}")
    assert checked["DDATA"] == SAMPLES + 1 and checked["NBIRTH"] == 2 and checked["seq wraps"] >= 1


def _num(v: Any) -> int:
    return int(v) if v is not None else -1


def _check_rules(msgs: list[dict[str, Any]]) -> dict[str, int]:
    """Assert the Sparkplug 3.0 rules on Tahu-decoded messages in arrival order; counts."""
    counts = dict.fromkeys(("NBIRTH", "DBIRTH", "DDATA", "NDATA", "NDEATH"), 0)
    counts["seq wraps"] = 0
    born: dict[str, str] | None = None  # DBIRTH's metric name → type
    bdseq: int | None = None
    seq: int | None = None
    for i, m in enumerate(msgs):
        parts = m["topic"].split("/")
        where = f"message {i} ({m['topic']})"
        # topics: spBv1.0/group/TYPE/node[/device]; device types name the device
        assert parts[0] == "spBv1.0" and parts[2] in TYPES, where
        assert len(parts) == (5 if parts[2].startswith("D") else 4), where
        p = m["payload"]
        kind = parts[2]
        counts[kind] = counts.get(kind, 0) + 1
        assert p.get("timestamp") is not None, f"{where}: no payload timestamp"
        names = {x["name"]: x for x in p.get("metrics", [])}
        if kind == "NDEATH":
            assert "seq" not in p or p["seq"] is None, f"{where}: NDEATH carries no seq"
            assert bdseq is not None and _num(names["bdSeq"]["value"]) == bdseq, f"{where}: NDEATH's bdSeq is NBIRTH's"
            continue
        assert p.get("seq") is not None, f"{where}: no seq"
        s = _num(p["seq"])
        assert 0 <= s <= 255, where
        if kind == "NBIRTH":
            assert s == 0, f"{where}: NBIRTH's seq is 0"
            assert names["bdSeq"]["type"] == "UInt64", where
            b = _num(names["bdSeq"]["value"])
            assert bdseq is None or b == bdseq, f"{where}: a rebirth in one session keeps bdSeq"
            bdseq, born = b, None
        else:
            assert seq is not None, f"{where}: before any NBIRTH"
            assert s == (seq + 1) % 256, f"{where}: seq {s} after {seq}"
            counts["seq wraps"] += s == 0
        seq = s
        if kind in ("NBIRTH", "DBIRTH"):  # every metric of a birth has a type and a time stamp
            for x in p["metrics"]:
                assert x.get("type") and x.get("timestamp") is not None, f"{where}: {x['name']} lacks type or timestamp"
        if kind == "DBIRTH":
            assert msgs[i - 1]["topic"].split("/")[2] == "NBIRTH", f"{where}: DBIRTH right after NBIRTH"
            born = {x["name"]: x["type"] for x in p["metrics"]}
        if kind == "DDATA":
            assert born is not None, f"{where}: DDATA before DBIRTH"
            for x in p["metrics"]:
                assert x["name"] in born, f"{where}: {x['name']} was not declared in DBIRTH"
                assert x["type"] == born[x["name"]], f"{where}: {x['name']} is {x['type']}, born {born[x['name']]}"
                assert x.get("timestamp") is not None, f"{where}: {x['name']} has no timestamp"
    assert counts["NDEATH"] == 1
    return counts

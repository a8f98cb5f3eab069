"""Sparkplug B 3.0 rules, checked on every message compd publishes to a real mosquitto.

Each is decoded by Eclipse Tahu's payload library (npm, unpacked into build/ by the Makefile), not by compd's code:
topics, births before data, bdSeq, seq, time stamps, every DDATA metric declared in DBIRTH with its type, aliases,
and a historian's view of the data sent by exception.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt

from compd.plant.sparkplug import DataType, MetricDef, encode
from compd.plant.telemetry import DEADBAND_BY_UNIT, Telemetry, device_metrics
from tests.conftest import ROOT

from .broker import Mosquitto
from .test_telemetry import feed, noisy, spec

TAHU = ROOT / "build" / "tools" / "node" / "node_modules"
DECODER = Path(__file__).with_name("tahu_decode.js")
TYPES = {"NBIRTH", "NDEATH", "NDATA", "NCMD", "DBIRTH", "DDEATH", "DDATA", "DCMD"}
SAMPLES = 600  # more messages in each half than seq has values: it wraps
FULL_REFRESH_S = 5.0  # 50 samples of 0.1 s: a dozen full refreshes in the run
# Tahu gives 64-bit integers as strings
_INT_TYPES = {"Int8", "Int16", "Int32", "Int64", "UInt8", "UInt16", "UInt32", "UInt64", "DateTime"}
_FLOAT_TYPES = {"Float", "Double"}


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
    assert (TAHU / "sparkplug-payload").is_dir(), (
        "no Tahu: `make build/tools/node/node_modules/sparkplug-payload/package.json`"
    )
    lines = "".join(json.dumps({"topic": t, "hex": b.hex()}) + "\n" for t, b in messages)
    r = subprocess.run(
        [node, str(DECODER)],
        input=lines,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "NODE_PATH": str(TAHU)},
    )
    assert r.returncode == 0, r.stderr
    out = [json.loads(ln) for ln in r.stdout.splitlines()]
    assert len(out) == len(messages) and not [o for o in out if "error" in o], [o for o in out if "error" in o][:3]
    for o, (_, b) in zip(out, messages, strict=True):
        o["bytes"] = len(b)
    return out


def _truth(n: int) -> dict[str, Any]:
    """What the full refresh of sample number n carries: the run feeds noisy(n − 1) as sample n."""
    return {"Sample": n, **{d.name: v for d, v in device_metrics(noisy(n - 1))}}


def test_every_message_of_a_session_keeps_the_sparkplug_rules(tmp_path: Path) -> None:
    with Mosquitto(tmp_path / "broker") as broker:
        raw = Raw(broker.port)
        tel = Telemetry(spec(tmp_path, broker.port, full_refresh_s=FULL_REFRESH_S))
        try:
            tel.start()
            t0 = time.time()
            feed(tel, 0, 1, t0, make=noisy)
            _wait(lambda: raw.count("DBIRTH") == 1, "the births")
            feed(tel, 1, SAMPLES // 2, t0, make=noisy)
            tel.event("axis_fault", "z", "input T_xi bad")
            # a model command this compd does not take: its answer goes out as NDATA Model/result
            model = encode(
                [(MetricDef("Node Control/Model", DataType.String), "kind: lvr")],
                timestamp_ms=int(time.time() * 1000),
                seq=None,
            )
            raw.client.publish("spBv1.0/plant/NCMD/edge1", model, qos=0)
            _wait(lambda: raw.count("DDATA") >= SAMPLES // 2 + 1 and raw.count("NDATA") >= 1, "the first half")
            # a host asks for a rebirth: births again in the same session (same bdSeq, seq from 0)
            cmd = encode(
                [(MetricDef("Node Control/Rebirth", DataType.Boolean), True)],
                timestamp_ms=int(time.time() * 1000),
                seq=None,
            )
            raw.client.publish("spBv1.0/plant/NCMD/edge1", cmd, qos=0)
            _wait(lambda: raw.count("DBIRTH") == 2, "the rebirth")
            feed(tel, SAMPLES // 2 + 1, SAMPLES - SAMPLES // 2 - 1, t0, make=noisy)
            _wait(lambda: raw.count("DDATA") >= SAMPLES + 1, "every sample")
        finally:
            tel.stop()
            _wait(lambda: raw.count("NDEATH") == 1, "the death certificate")
            raw.stop()
        decoded = _tahu([(t, b) for t, b in raw.messages if t.split("/")[2] != "NCMD"])
    checked = _check_rules(decoded, _truth)
    sizes = checked.pop("sizes")
    print(
        f"Sparkplug B 3.0 rules checked on {len(decoded)} messages decoded by Eclipse Tahu sparkplug-payload"
        f" 1.0.3: {', '.join(f'{k} {v}' for k, v in checked.items())}; DDATA bytes per sample:"
        f" {', '.join(f'{k} {v:.1f}' for k, v in sizes.items())}"
    )
    assert checked["DDATA"] == SAMPLES + 1 and checked["NBIRTH"] == 2 and checked["seq wraps"] >= 1
    assert checked["NDATA"] >= 1
    # report by exception: whole after each birth and every FULL_REFRESH_S of sample time, else the news
    assert checked["full refreshes"] >= SAMPLES * 0.1 / FULL_REFRESH_S and checked["exceptions"] > SAMPLES * 0.8
    assert checked["samples reconstructed"] == SAMPLES and checked["rebirths that kept the aliases"] == 1
    assert sizes["mean"] < sizes["full refresh"] / 3  # what the exceptions are for


def _num(v: Any) -> int:
    return int(v) if v is not None else -1


def _value(x: dict[str, Any], datatype: str) -> Any:
    """A Tahu-decoded metric's value in Python's terms (64-bit integers come as strings)."""
    v = x.get("value")
    if v is None:
        return None
    if datatype in _INT_TYPES:
        return int(v)
    if datatype in _FLOAT_TYPES:
        return float(v)
    return v


def _same(datatype: str, unit: str | None, held: Any, true: Any) -> bool:
    """A historian's value is the true one: a Float/Double within its unit's deadband (compd's
    report by exception), anything else equal; null only for null."""
    if held is None or true is None:
        return held is None and true is None
    if datatype in _FLOAT_TYPES:
        return abs(float(held) - float(true)) <= DEADBAND_BY_UNIT.get(unit or "", 0.0) + 1e-9
    return bool(held == true)


def _check_rules(msgs: list[dict[str, Any]], truth: Callable[[int], dict[str, Any]]) -> dict[str, Any]:
    """Assert the Sparkplug 3.0 rules on Tahu-decoded messages in arrival order, and that a historian
    that holds the births and applies every DDATA's metrics on top holds `truth(Sample)` after each
    sample (equal, or within the deadbands for Double); counts, and the DDATA sizes."""
    counts: dict[str, Any] = dict.fromkeys(("NBIRTH", "DBIRTH", "DDATA", "NDATA", "NDEATH"), 0)
    counts |= dict.fromkeys(
        (
            "seq wraps",
            "full refreshes",
            "exceptions",
            "events",
            "samples reconstructed",
            "rebirths that kept the aliases",
            "aliases",
        ),
        0,
    )
    born: dict[str, dict[str, Any]] = {}  # per node ("") or device id: alias → (name, type, unit)
    node_aliases: dict[str, tuple[str, str]] = {}  # alias → (device or "", name), across the node's births
    before: dict[str, dict[str, str]] = {}  # per device: name → alias of the births before this one
    state: dict[str, Any] = {}  # the device's metrics as a historian holds them
    whole: set[str] = set()  # the metrics a full refresh carries (the DBIRTH's sample metrics)
    fresh = False  # no sample since the last birth: the next one must come whole
    last_truth: dict[str, Any] | None = None
    bdseq: int | None = None
    seq: int | None = None
    sizes: dict[str, list[int]] = {"exception": [], "full refresh": []}
    for i, m in enumerate(msgs):
        parts = m["topic"].split("/")
        where = f"message {i} ({m['topic']})"
        # topics: spBv1.0/group/TYPE/node[/device]; device types name the device
        assert parts[0] == "spBv1.0" and parts[2] in TYPES, where
        assert len(parts) == (5 if parts[2].startswith("D") else 4), where
        p = m["payload"]
        kind = parts[2]
        scope = parts[4] if len(parts) == 5 else ""
        counts[kind] = counts.get(kind, 0) + 1
        assert p.get("timestamp") is not None, f"{where}: no payload timestamp"
        metrics = p.get("metrics", [])
        if kind == "NDEATH":
            names = {x["name"]: x for x in metrics}
            assert "seq" not in p or p["seq"] is None, f"{where}: NDEATH carries no seq"
            assert bdseq is not None and _num(names["bdSeq"]["value"]) == bdseq, f"{where}: NDEATH's bdSeq is NBIRTH's"
            continue
        assert p.get("seq") is not None, f"{where}: no seq"
        s = _num(p["seq"])
        assert 0 <= s <= 255, where
        if kind == "NBIRTH":
            names = {x["name"]: x for x in metrics}
            assert s == 0, f"{where}: NBIRTH's seq is 0"
            assert names["bdSeq"]["type"] == "UInt64", where
            b = _num(names["bdSeq"]["value"])
            assert bdseq is None or b == bdseq, f"{where}: a rebirth in one session keeps bdSeq"
            bdseq = b
            born = {}  # a node's birth starts its aliases afresh: its devices are born again after it
            node_aliases = {}
        else:
            assert seq is not None, f"{where}: before any NBIRTH"
            assert s == (seq + 1) % 256, f"{where}: seq {s} after {seq}"
            counts["seq wraps"] += s == 0
        seq = s
        if kind in ("NBIRTH", "DBIRTH"):
            table: dict[str, Any] = {}
            for x in metrics:
                # every metric of a birth has a name, a type and a time stamp ...
                assert x.get("name") and x.get("type") and x.get("timestamp") is not None, (
                    f"{where}: {x.get('name')} lacks name, type or timestamp"
                )
                # ... and an alias, unique across the node and its devices; but Node Control/Rebirth,
                # which has none (Sparkplug 3.0: an NBIRTH MUST NOT alias it)
                if x["name"] == "Node Control/Rebirth":
                    assert kind == "NBIRTH" and "alias" not in x, f"{where}: Node Control/Rebirth has an alias"
                    continue
                assert "alias" in x, f"{where}: {x['name']} has no alias"
                alias = str(x["alias"])
                assert alias not in table and alias not in node_aliases, f"{where}: alias {alias} given twice"
                table[alias] = (x["name"], x["type"], (x.get("properties") or {}).get("engUnit", {}).get("value"))
                node_aliases[alias] = (scope, x["name"])
            counts["aliases"] = len(node_aliases)
            aliases = {v[0]: a for a, v in table.items()}
            if scope in before:  # a rebirth: compd keeps the aliases a metric had
                kept = all(aliases.get(n) == a for n, a in before[scope].items())
                counts["rebirths that kept the aliases"] += kept and kind == "DBIRTH"
            before[scope] = aliases
            born[scope] = table
        if kind == "DBIRTH":
            assert msgs[i - 1]["topic"].split("/")[2] == "NBIRTH", f"{where}: DBIRTH right after NBIRTH"
            state = {x["name"]: _value(x, x["type"]) for x in metrics}
            whole = set(_truth_names(truth))
            assert whole <= set(state), f"{where}: {whole - set(state)} not born"
            fresh = True
        if kind in ("NDATA", "DDATA"):
            assert scope in born, f"{where}: {kind} before the birth of its {'device' if scope else 'node'}"
            got: dict[str, Any] = {}
            for x in metrics:
                # by alias only, declared by the birth of this node or device, of its type, time stamped
                assert "alias" in x and not x.get("name"), f"{where}: a data metric not by alias alone: {x}"
                alias = str(x["alias"])
                assert alias in born[scope], f"{where}: alias {alias} was not declared in the {scope or 'node'}'s birth"
                name, datatype, unit = born[scope][alias]
                assert x["type"] == datatype, f"{where}: {name} is {x['type']}, born {datatype}"
                assert x.get("timestamp") is not None, f"{where}: {name} has no timestamp"
                assert name not in got, f"{where}: {name} twice"
                got[name] = _value(x, datatype)
            if kind == "DDATA" and "Sample" not in got:
                counts["events"] += 1
                assert set(got) == {"Event/kind", "Event/subject", "Event/reason"}, f"{where}: an event goes whole"
            elif kind == "DDATA":
                n = got["Sample"]
                full = set(got) >= whole
                assert full or not fresh, f"{where}: the first sample after a birth is not whole"
                true = truth(n)
                types = {v[0]: (v[1], v[2]) for v in born[scope].values()}
                if full and last_truth is not None and not fresh:
                    # a full refresh agrees with what the historian held on every metric whose true
                    # value did not change since the previous sample
                    for k, v in got.items():
                        dt, unit = types[k]
                        if _same(dt, unit, last_truth.get(k), true.get(k)):
                            assert _same(dt, unit, state.get(k), v), f"{where}: {k} held {state.get(k)}, refresh {v}"
                state.update(got)
                for k, v in true.items():
                    dt, unit = types[k]
                    assert _same(dt, unit, state.get(k), v), f"{where}: sample {n}: {k} held {state.get(k)}, is {v}"
                counts["samples reconstructed"] += 1
                counts["full refreshes" if full else "exceptions"] += 1
                sizes["full refresh" if full else "exception"].append(m["bytes"])
                fresh = False
                last_truth = true
    assert counts["NDEATH"] == 1
    every = sizes["exception"] + sizes["full refresh"]
    counts["sizes"] = {"mean": sum(every) / len(every), **{k: sum(v) / max(len(v), 1) for k, v in sizes.items()}}
    return counts


def _truth_names(truth: Callable[[int], dict[str, Any]]) -> list[str]:
    """The metrics a sample carries whole (those of the first sample's truth)."""
    return list(truth(1))

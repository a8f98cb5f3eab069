"""`compd sparkplug-watch`: bad options are one line and exit 2, a broker that is not there exit 1.

A message by an alias no birth declared is shown by its alias; after a rebirth is asked, the node's messages
sent before its birth are left out.
"""

from __future__ import annotations

import io
import socket
import subprocess
import sys

import pytest

from compd.cli.plant import RebirthGate, describe
from compd.plant.sparkplug import AliasResolver, DataType, MetricDef, encode, topic


def compd(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "compd", "sparkplug-watch", *argv], capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        ((), "give --config or --host"),
        (("--host", "127.0.0.1", "--config", "x.yaml"), "give --config or --host"),
        (("--host", "127.0.0.1", "--count", "0"), "--count must be at least 1"),
        (("--host", "127.0.0.1", "--rebirth"), "--rebirth needs the group and the edge node"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(argv: tuple[str, ...], says: str) -> None:
    r = compd(*argv)
    assert r.returncode == 2 and says in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr


def test_no_broker_is_exit_1_naming_it() -> None:
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = compd("--host", "127.0.0.1", "--port", str(port), "--count", "1")
    assert r.returncode == 1 and f"cannot reach the broker at 127.0.0.1:{port}" in r.stderr, r.stderr


def test_births_name_the_data_and_an_unknown_alias_is_shown_as_such() -> None:
    out, units, resolver = io.StringIO(), {}, AliasResolver()
    metric = MetricDef("Axis/z/correction_um", DataType.Double, "µm")
    birth = encode(
        [(metric, -3.25)], timestamp_ms=1_795_000_000_000, seq=1, with_properties=True, aliases={metric.name: 13}
    )
    data = encode([(metric, -3.5)], timestamp_ms=1_795_000_001_000, seq=2, aliases={metric.name: 13}, names=False)
    describe(topic("desk", "DDATA", "cell1", "spindle"), data, resolver, units, out)  # before any birth
    describe(topic("desk", "DBIRTH", "cell1", "spindle"), birth, resolver, units, out)
    describe(topic("desk", "DDATA", "cell1", "spindle"), data, resolver, units, out)
    lines = out.getvalue().splitlines()
    assert "  alias 13 = -3.5  (Double)" in lines
    assert any(line.startswith("  (aliases 13: no birth of this node seen") for line in lines)
    assert "  Axis/z/correction_um = -3.25 µm  (Double, alias 13)" in lines
    assert "  Axis/z/correction_um = -3.5 µm  (Double)" in lines


def test_after_a_rebirth_ask_the_nodes_messages_before_its_birth_are_left_out() -> None:
    """A DDATA the node sent before it saw the NCMD (its old sequence, by aliases) is not shown nor counted;
    the NCMD itself, another node's messages and everything from the NBIRTH on are."""
    gate = RebirthGate("desk", "cell1")
    arrivals = [
        (topic("desk", "DDATA", "cell1", "spindle"), False),  # in flight when the rebirth was asked
        (topic("desk", "NCMD", "cell1"), True),
        (topic("desk", "NDATA", "cell1"), False),
        (topic("desk", "DDATA", "cell2", "spindle"), True),
        (topic("hall", "DDATA", "cell1", "spindle"), True),
        ("spBv1.0/STATE/scada", True),
        (topic("desk", "NBIRTH", "cell1"), True),
        (topic("desk", "DBIRTH", "cell1", "spindle"), True),
        (topic("desk", "DDATA", "cell1", "spindle"), True),
    ]
    assert [gate.admit(t) for t, _ in arrivals] == [shown for _, shown in arrivals]
    assert gate.born and gate.held == 2
    ungated = RebirthGate(None, None)  # no rebirth asked: everything shows
    assert all(ungated.admit(t) for t, _ in arrivals) and ungated.held == 0

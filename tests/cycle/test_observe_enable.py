"""Observe mode: "enabled" means the machine has the enabled word, so every channel says no.

The ObserveSink writes the word 0x0000 (every enable bit off) while the guard's own bit is on:
status.json, `compd status`, the metrics, Sparkplug and OPC UA all derive from the snapshot's
per-axis `enable`, which must be false; `guard_enable` keeps the guard's bit, `word` the word
the loop computed and `word_at_machine` the word the sink writes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from compd.config import load_config
from compd.daemon.app import App
from compd.plant.telemetry import device_metrics
from compd.service.status import jsonable, render, snapshot
from compd.sinks.observe import ObserveSink
from tests.service_helpers import sim_config

CYCLE = 3000  # the sim spindle is warm and the axis normal by then (tests/service/test_status.py)


def _mid_run(tmp_path: Path, *, observe: bool, flag: bool | None = None) -> dict[str, Any]:
    """The snapshot of a sim run taken inside cycle CYCLE (nothing moves under it), with the
    loop's word and the card's word at that moment. `flag`: the observe argument given to
    `snapshot` (default: the run's own)."""
    app = App(load_config(sim_config(tmp_path, duration_s=3600)), observe=observe)
    taken: dict[str, Any] = {}

    def take(loop: Any, now: float) -> None:
        if loop.stats.cycles == CYCLE:
            taken["snap"] = jsonable(snapshot(loop, state="running", observe=observe if flag is None else flag))
            taken["word"] = loop.word
            inner = loop.sink.inner if isinstance(loop.sink, ObserveSink) else loop.sink
            taken["card"] = inner.card.read_do_word(0)

    app.loop.observers.append(take)
    app.run()
    assert "snap" in taken, "the run ended before the snapshot's cycle"
    return taken


@pytest.fixture(scope="module")
def observed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return _mid_run(tmp_path_factory.mktemp("observe"), observe=True)


def test_observe_mode_snapshot_says_disabled_while_the_guard_enables(observed: dict[str, Any]) -> None:
    snap, word = observed["snap"], observed["word"]
    assert word != 0, "the loop computed no correction to hold back"
    assert observed["card"] == 0  # what the machine has
    z = snap["axes"]["z"]
    assert z["state"] == "normal" and z["guard_enable"] is True  # the guard's own bit is on
    assert z["enable"] is False  # ... but the machine has the word 0: not enabled
    assert snap["word"] == f"0x{word:04X}"  # the word the loop computed
    assert snap["word_at_machine"] == "0x0000"  # the word the sink writes
    assert snap["sink"]["word"] == "0x0000" and snap["sink"]["would_write"] == f"0x{word:04X}"
    assert json.loads(json.dumps(snap, allow_nan=False)) == snap


def test_the_observe_sink_alone_is_enough_to_say_disabled(tmp_path: Path) -> None:
    """A caller that passes observe=False for a loop whose sink is an ObserveSink: the sink's
    status says observe, so nothing claims the axis is enabled."""
    snap = _mid_run(tmp_path, observe=True, flag=False)["snap"]
    assert snap["axes"]["z"]["guard_enable"] is True and snap["axes"]["z"]["enable"] is False
    assert snap["word_at_machine"] == "0x0000"


def test_without_observe_the_axis_is_enabled_and_the_word_is_at_the_machine(tmp_path: Path) -> None:
    taken = _mid_run(tmp_path, observe=False)
    snap = taken["snap"]
    assert snap["axes"]["z"]["enable"] is True and snap["axes"]["z"]["guard_enable"] is True
    assert snap["word"] == snap["word_at_machine"] == f"0x{taken['word']:04X}" == f"0x{taken['card']:04X}"


def test_status_text_in_observe_mode(observed: dict[str, Any]) -> None:
    snap = observed["snap"]
    text = render(snap, True, "running")
    z = next(ln for ln in text.splitlines() if ln.startswith("z "))
    assert z.split()[5] == "no"  # the `enabled` column
    word = next(ln for ln in text.splitlines() if ln.startswith("word: "))
    assert word.startswith(f"word: {snap['word']} computed, held back by observe mode (on the output: 0x0000)")


def test_metrics_say_disabled_in_observe_mode(observed: dict[str, Any]) -> None:
    pytest.importorskip("prometheus_client")  # the `metrics` extra; the `test` extra installs it
    from compd.service.metrics import SnapshotCollector

    c = SnapshotCollector()
    c.update(observed["snap"], [], 0, 0.0)
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value for f in c.collect() for s in f.samples}
    assert samples[("compd_axis_enabled", (("axis", "z"),))] == 0.0
    assert samples[("compd_observe_mode", ())] == 1.0


def test_sparkplug_says_disabled_in_observe_mode(observed: dict[str, Any]) -> None:
    m = {d.name: v for d, v in device_metrics(observed["snap"])}
    assert m["Axis/z/enable"] is False
    assert m["Observe"] is True


def test_sparkplug_and_opcua_never_say_enabled_in_observe_mode_even_from_an_old_status() -> None:
    """A snapshot that has `observe` true but an axis `enable` true (a status from before the
    fix): the plant channels still say disabled."""
    snap = {
        "state": "running",
        "observe": True,
        "word": "0x5000",
        "axes": {
            "z": {"correction_um": -1.0, "target_um": -1.0, "prediction_um": 1.0, "enable": True, "state": "normal"}
        },
        "signals": {},
        "model": {"kind": "xi_spindle", "fit": {}},
    }
    assert {d.name: v for d, v in device_metrics(snap)}["Axis/z/enable"] is False
    pytest.importorskip("asyncua")  # the `plant` extra
    from compd.plant.opcua import address_space, data_values

    variables = address_space(snap)
    values, _ = data_values(variables, snap)
    enable = dict(zip((v.node_id for v in variables), values, strict=True))["compd.Axes.z.Enable"]
    assert enable.Value.Value is False and enable.StatusCode.is_good()


def test_opcua_enable_is_false_in_observe_mode(observed: dict[str, Any]) -> None:
    pytest.importorskip("asyncua")  # the `plant` extra
    from compd.plant.opcua import address_space, data_values

    snap = observed["snap"]
    variables = address_space(snap)
    values, problems = data_values(variables, snap)
    by_id = dict(zip((v.node_id for v in variables), values, strict=True))
    assert by_id["compd.Axes.z.Enable"].Value.Value is False
    assert by_id["compd.Observe"].Value.Value is True
    assert not any("Enable" in p for p in problems), problems


def test_a_sink_whose_link_is_down_is_not_enabled_and_confirms_no_word(tmp_path: Path) -> None:
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    taken: dict[str, Any] = {}

    def take(loop: Any, now: float) -> None:
        if loop.stats.cycles == CYCLE:
            real = loop.sink.link_state
            loop.sink.link_state = lambda: "down"  # the card unreachable
            try:
                taken["snap"] = snapshot(loop, state="running", observe=False)
            finally:
                loop.sink.link_state = real

    app.loop.observers.append(take)
    app.run()
    snap = taken["snap"]
    assert snap["axes"]["z"]["guard_enable"] is True and snap["axes"]["z"]["enable"] is None  # not confirmed
    assert snap["word_at_machine"] is None  # nothing is confirmed at the machine
    text = render(jsonable(snap), True, "running")
    assert "OUTPUT NOT REACHING THE MACHINE" in text


def test_observe_mode_takes_a_correction_found_at_the_card_to_zero_one_lsb_at_a_time() -> None:
    """A card still holding the word of a run that was killed: observe mode does not drop it to
    0x0000 at once (a step at the machine) but walks it down at the guard's ramp, one LSB at a
    time, then holds the safe word."""
    from compd.codec import codes_from_word, encode
    from compd.plc.pci1756 import Pci1756Card
    from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink

    card = Pci1756Card()
    card.write_do_word(0, encode(-9.0, 4.0))  # what the killed run left on the lines
    sink = ObserveSink(Pci1756Sink(Pci1756Config(kind="pci1756"), card=card), ramp_um_per_s=5.0)
    sink.bind(["z", "x"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0) and sink.held_um() == {"z": -9.0, "x": 4.0}
    codes = []
    for k in range(2000):  # 10 ms cycles: 20 s, the ramp takes 1.8 s
        sink.write(encode(30.0, 30.0), np.zeros(2), np.ones(2, dtype=bool), k == 0, 0.01 * k)
        codes.append(codes_from_word(card.read_do_word(0)))
    steps = np.abs(np.diff(np.array([(-9, 4)] + codes), axis=0))
    assert steps.max() <= 1, "the word stepped"
    assert codes[-1] == (0, 0) and card.read_do_word(0) == 0
    first_zero = next(i for i, c in enumerate(codes) if c[0] == 0)
    assert 0.01 * first_zero >= 9.0 / 5.0 - 0.05  # no faster than the ramp

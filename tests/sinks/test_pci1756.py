"""pci1756 sink: word bytes, heartbeat, safe output (on the software PLC's card in process)."""

from __future__ import annotations

import numpy as np
import pytest

from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink


def make_sink(**kw) -> Pci1756Sink:  # noqa: ANN003
    sink = Pci1756Sink(Pci1756Config(kind="pci1756", **kw))
    sink.bind(["x1", "x2"], 1.0)
    return sink


def test_word_on_configured_port_and_heartbeat_toggles() -> None:
    sink = make_sink(word_port=2, heartbeat_bit=0)
    corr = np.array([5.0, -3.0])
    en = np.array([True, True])
    beats = []
    for _ in range(4):
        sink.write(0xC543, corr, en, False, 0.0)
        beats.append(sink.card.read_do() & 1)
    assert sink.card.read_do_word(2) == 0xC543
    assert beats == [1, 0, 1, 0]
    out = np.zeros(2)
    sink.applied_um(out)
    assert out.tolist() == [5.0, -3.0]
    sink.safe()
    assert sink.card.read_do_word(2) == 0
    sink.applied_um(out)
    assert out.tolist() == [0.0, 0.0]


def test_heartbeat_may_not_overlap_the_word() -> None:
    with pytest.raises(ValueError, match="heartbeat"):
        Pci1756Config(kind="pci1756", word_port=1, heartbeat_bit=12)

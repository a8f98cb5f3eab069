"""pci1756 sink: word bytes, heartbeat, safe output (on the software PLC's card in process)."""

from __future__ import annotations

import numpy as np
import pytest

from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink


def make_sink(**kw) -> Pci1756Sink:  # noqa: ANN003
    sink = Pci1756Sink(Pci1756Config(kind="pci1756", **kw))
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    assert sink.sync(0.0)  # the card's lines read back before anything is written
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


def test_write_rows_equals_writing_row_by_row() -> None:
    """`write_rows` writes only the rows with a new word (and the heartbeat as often as every row
    would have): the applied and commanded word and the card's lines as writing every row."""
    from compd.codec import word_from_codes
    from compd.sinks.base import Sink

    rng = np.random.default_rng(5)
    n = 1001
    codes = np.clip(np.cumsum(rng.choice([0, 0, 0, 1, -1], (n, 2)), axis=0), -63, 63)
    words = np.array([word_from_codes(int(a), int(b)) for a, b in codes])
    changed = np.r_[True, words[1:] != words[:-1]]
    t = np.arange(n, dtype=float)
    corr, en = np.zeros((n, 2)), np.ones((n, 2), dtype=bool)
    ref, got = make_sink(strobe_bit=20), make_sink(strobe_bit=20)
    a1, c1, a2, c2 = (np.zeros((n, 2)) for _ in range(4))
    Sink.write_rows(ref, t, words, changed, corr, en, a1, c1)
    got.write_rows(t, words, changed, corr, en, a2, c2)
    np.testing.assert_array_equal(a2, a1)
    np.testing.assert_array_equal(c2, a1)
    assert got.card.read_do() == ref.card.read_do() and got.writes == ref.writes == n

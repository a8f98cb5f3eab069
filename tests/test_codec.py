"""The 16-bit word of paper 002 (docs/formats.md): examples, properties, no-chatter rule, CLI."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compd import codec
from compd.cli import main

finite = st.floats(min_value=-200, max_value=200, allow_nan=False, allow_infinity=False)
lsbs = st.sampled_from([0.1, 0.5, 1.0, 2.0])


@pytest.mark.parametrize(
    ("c1", "c2", "word"),
    [(5, -3, 0xC543), (0.8, 70, 0x00FF), (-1.0, 1.01, 0x00C1), (0, 0, 0x0000), (-63, 63, 0x7FFF)],
)
def test_spec_examples(c1: float, c2: float, word: int) -> None:
    assert codec.encode(c1, c2) == word


def test_saturation_is_reported() -> None:
    word, s1, s2 = codec.encode_ex(0.8, 70)
    assert word == 0x00FF and not s1 and s2


def test_decode_example() -> None:
    x1, x2 = codec.decode(0xC543)
    assert x1 == (1, True, 5)
    assert x2 == (-1, True, 3)
    assert codec.word_to_um(0xC543) == (5.0, -3.0)


@given(finite, finite, lsbs)
def test_round_trip_within_half_lsb(c1: float, c2: float, lsb: float) -> None:
    deadband = 1.0
    word, s1, s2 = codec.encode_ex(c1, c2, lsb, deadband)
    back = codec.word_to_um(word, lsb)
    codes = codec.decode(word)
    for c, b, sat, code in ((c1, back[0], s1, codes[0]), (c2, back[1], s2, codes[1])):
        assert code.magnitude <= 63
        if abs(c) <= deadband:
            assert b == 0.0
        elif sat:
            assert abs(c) / lsb > 63.5 - 1e-9 or math.floor(abs(c) / lsb + 0.5) > 63
            assert b == math.copysign(63 * lsb, c)
        elif b != 0.0:
            assert abs(b - c) <= lsb / 2 + 1e-9
            assert math.copysign(1, b) == math.copysign(1, c)


@given(st.integers(min_value=0, max_value=0xFFFF))
def test_decode_encode_word(word: int) -> None:
    """Every enabled byte re-encodes to itself from its decoded value."""
    x1, x2 = codec.decode(word)
    for code, byte in ((x1, word >> 8), (x2, word & 0xFF)):
        assert 0 <= code.magnitude <= 63
        if code.enable and code.magnitude > 1:
            assert codec.encode_byte(code.direction * code.magnitude)[0] == byte


def test_word_from_codes() -> None:
    """The word of codes already in LSB: what the FANUC sink steps through."""
    assert codec.word_from_codes(5, -3) == codec.encode(5, -3) == 0xC543
    assert codec.word_from_codes(0, 70) == 0x00FF  # clamped to 63, disabled axis 0x00
    assert codec.word_bytes(0xC543) == (0xC5, 0x43)
    assert codec.join_bytes(0xC5, 0x43) == 0xC543


@given(st.integers(min_value=-63, max_value=63), st.integers(min_value=-63, max_value=63))
def test_codes_round_trip(q1: int, q2: int) -> None:
    assert codec.codes_from_word(codec.word_from_codes(q1, q2)) == (q1, q2)


def test_codes_of_a_disabled_byte_are_zero() -> None:
    assert codec.codes_from_word(0x8543) == (0, -3)  # high byte: enable bit off


def test_nan_and_inf_encode_disabled() -> None:
    assert codec.encode(math.nan, math.inf) == 0


def test_bad_lsb_rejected() -> None:
    with pytest.raises(ValueError):
        codec.encode(1, 1, lsb_um=0)


def test_no_chatter_at_rounding_boundary() -> None:
    enc = codec.Encoder()
    assert enc.update(5.0, 0.0)
    first = enc.word
    # hovering around the 5.5 rounding boundary must not toggle the word
    for c in (5.49, 5.51, 5.49, 5.52, 5.48, 5.9):
        assert not enc.update(c, 0.0)
        assert enc.word == first
    assert enc.update(6.0, 0.0)  # moved by a full dead-band from 5.0
    assert codec.decode(enc.word)[0].magnitude == 6


def _slewed(targets: list[float], slew_um_per_s: float, period_s: float) -> list[float]:
    """What the guard offers the codec: each target approached at the slew limit."""
    out, c = [], 0.0
    for target in targets:
        step = slew_um_per_s * period_s
        c += max(-step, min(step, target - c))
        out.append(c)
    return out


def _walk(enc: codec.Encoder, cs: list[float], period_s: float) -> list[int]:
    """The high byte's signed code after each cycle."""
    codes = []
    for c in cs:
        enc.update(c, 0.0, dt_s=period_s)
        x1 = codec.decode(enc.word)[0]
        codes.append(x1.direction * x1.magnitude if x1.enable else 0)
    return codes


def _assert_paced(codes: list[int], period_s: float, lsb_um: float, slew_um_per_s: float) -> None:
    """One LSB at a time, and m steps take at least m·lsb/slew less one cycle."""
    steps = [k for k in range(1, len(codes)) if codes[k] != codes[k - 1]]
    for k in steps:
        assert abs(codes[k] - codes[k - 1]) == 1, (k, codes[k - 1], codes[k])
    for a, ka in enumerate(steps):
        for m, kb in enumerate(steps[a + 1 :], start=1):
            assert (kb - ka + 1) * period_s >= m * lsb_um / slew_um_per_s - 1e-9, (ka, kb, m)


def test_word_never_steps_faster_than_the_slew() -> None:
    """The audit: slew 2 µm/s, 10 ms cycles, dead-band 3 µm — the old encoder jumped 3 → 6 LSB."""
    period_s, slew = 0.01, 2.0
    enc = codec.Encoder(1.0, 3.0, slew, period_s)
    cs = _slewed([20.0] * 1500 + [-5.0] * 2000, slew, period_s)
    codes = _walk(enc, cs, period_s)
    _assert_paced(codes, period_s, 1.0, slew)
    assert codes[1499] >= 17 and codes[-1] == -5


def test_held_word_stays_within_the_deadband() -> None:
    """The audit: −11.22 µm was sent as −10 µm for a whole run. Now the word settles at −11."""
    period_s, slew = 0.01, 5.0
    enc = codec.Encoder(1.0, 1.0, slew, period_s)
    cs = _slewed([-11.22] * 1000, slew, period_s)
    codes = _walk(enc, cs, period_s)
    for c, q in zip(cs, codes, strict=True):
        assert abs(q - c) <= 1.0 + 2 * slew * period_s
    assert codes[-1] == -11


@settings(max_examples=500, deadline=None)
@given(
    targets=st.lists(st.floats(-80, 80), min_size=1, max_size=8),
    hold_cycles=st.integers(1, 400),
    slew=st.floats(0.1, 200.0),
    lsb=st.sampled_from([0.1, 0.5, 1.0, 2.0]),
    deadband=st.floats(0.0, 5.0),
    period_s=st.sampled_from([0.001, 0.002, 0.01]),
)
def test_word_walks_within_band_at_slew_pace(
    targets: list[float], hold_cycles: int, slew: float, lsb: float, deadband: float, period_s: float
) -> None:
    enc = codec.Encoder(lsb, deadband, slew, period_s)
    cs = _slewed([t for t in targets for _ in range(hold_cycles)], slew, period_s)
    codes = _walk(enc, cs, period_s)
    if slew * period_s < lsb:  # the live loop: every cycle is shorter than one LSB at the slew
        _assert_paced(codes, period_s, lsb, slew)
    band = max(deadband, lsb)
    for c, q in zip(cs, codes, strict=True):
        if abs(c) < 63 * lsb:  # not saturated
            assert abs(q * lsb - c) <= band + 2 * slew * period_s + 1e-9


def test_replay_rows_longer_than_one_lsb_at_the_slew() -> None:
    """At one row per second the word may move slew·dt per row, not one LSB per row."""
    enc = codec.Encoder(1.0, 1.0, 5.0, period_s=1.0)
    codes = _walk(enc, [5.0, 10.0, 15.0], 1.0)
    assert codes == [5, 10, 15]


def test_after_a_stall_the_word_catches_up_one_lsb_a_cycle() -> None:
    """A cycle 0.2 s late licenses 4 LSB at 20 µm/s (the guard moves 4 µm in it); the word
    spends them one LSB a cycle, then banks no more than one LSB once it has settled."""
    enc = codec.Encoder(1.0, 1.0, 20.0, period_s=0.01)
    _walk(enc, [0.0] * 10, 0.01)
    codes = _walk(enc, [4.0], 0.2) + _walk(enc, [4.0] * 5, 0.01)
    assert codes == [1, 2, 3, 4, 4, 4]
    codes = _walk(enc, [4.0] * 300, 0.01) + _walk(enc, [9.0], 0.01) + _walk(enc, [9.0] * 30, 0.01)
    steps = [k for k in range(1, len(codes)) if codes[k] != codes[k - 1]]
    assert codes[-1] == 9 and steps[1] - steps[0] >= 4  # after the bank, the slew's pace


def test_reload_keeps_the_held_word() -> None:
    old = codec.Encoder(1.0, 1.0, 2.0)
    _walk(old, _slewed([-9.0] * 2000, 2.0, 0.01), 0.01)
    new = codec.Encoder(1.0, 1.0, 2.0)
    new.adopt(old)
    assert new.word == old.word
    assert not new.update(-9.0, 0.0, dt_s=0.01)


def test_encoder_enable_change_always_emits() -> None:
    enc = codec.Encoder()
    enc.update(10.0, -10.0)
    assert enc.update(10.0, -10.0, en1=False)
    assert enc.word >> 8 == 0


def test_cli_encode(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["encode", "5", "-3"]) == 0
    out = capsys.readouterr().out
    assert out.split()[0] == "0xC543"


def test_cli_encode_negative_first_argument() -> None:
    r = subprocess.run([sys.executable, "-m", "compd", "encode", "--", "-5", "3"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[0] == "0x45C3"


def test_cli_decode(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", "0xC543"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "X1" in out[0] and "+5" in out[0] and "enable 1" in out[0]
    assert "X2" in out[1] and "-3" in out[1]


def test_cli_decode_bad_word(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", "0x1FFFF"]) == 2
    assert "16 bits" in capsys.readouterr().err


def test_tiny_lsb_saturates_instead_of_overflowing():
    """|c|/LSB overflows to inf for a denormal LSB: the byte saturates, nothing raises."""
    from compd.codec import encode_ex

    word, s1, s2 = encode_ex(5.0, -5.0, lsb_um=1e-320, deadband_um=0.0)
    assert word == 0xFF7F and s1 and s2


def test_update_rows_equals_update_row_by_row() -> None:
    """The replay's `update_rows` gives the words, changes and state that `update` gives row by
    row: walks, dead-band, saturation, disabled axes, NaN, no time or much time per row."""
    import numpy as np

    rng = np.random.default_rng(11)
    n = 5000
    c = np.cumsum(rng.normal(0.0, 0.8, (n, 2)), axis=0)
    c[3000:3200, 0] = 80.0  # saturated
    c[rng.random((n, 2)) < 0.005] = np.nan
    en = rng.random((n, 2)) > 0.01
    en[4000:4050, 1] = False
    dt = rng.choice([0.0, 0.002, 0.5, 1.0, 10.0, 1e9], n, p=[0.02, 0.3, 0.2, 0.35, 0.12, 0.01])
    for period in (0.002, math.inf):
        ref = codec.Encoder(0.5, 1.0, 4.0, period_s=period)
        words, changed = np.zeros(n, np.int64), np.zeros(n, bool)
        for i in range(n):
            changed[i] = ref.update(c[i, 0], c[i, 1], bool(en[i, 0]), bool(en[i, 1]), float(dt[i]))
            words[i] = ref.word
        got = codec.Encoder(0.5, 1.0, 4.0, period_s=period)
        w2, ch2 = np.zeros(n, np.int64), np.zeros(n, bool)
        got.update_rows(c[:, 0], c[:, 1], en[:, 0], en[:, 1], dt, w2, ch2)
        np.testing.assert_array_equal(w2, words)
        np.testing.assert_array_equal(ch2, changed)
        assert (got.codes, got.saturated, got.saturations, got.words_emitted) == (
            ref.codes,
            ref.saturated,
            ref.saturations,
            ref.words_emitted,
        )
        assert got._budget == ref._budget and got._moving == ref._moving


def test_an_infinite_period_walks_what_the_time_licensed() -> None:
    """A replay sets an infinite period: a row 10 s after the last walks 10 s of slew (0.5 µm/s:
    5 LSB; the first also spends the LSB a settled word banks), where a loop period of 1 s at
    that slew would move it one LSB a row."""
    enc = codec.Encoder(1.0, 1.0, 0.5, period_s=math.inf)
    assert _walk(enc, [0.0, 20.0, 20.0], 10.0) == [0, 6, 11]
    per_cycle = codec.Encoder(1.0, 1.0, 0.5, period_s=1.0)
    assert _walk(per_cycle, [0.0, 20.0, 20.0], 10.0) == [0, 1, 2]

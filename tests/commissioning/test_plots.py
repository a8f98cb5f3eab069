"""compd.commissioning.plots and `compd plot`: the word decoded with the codec, bands from the log, bad logs exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from compd.cli import main
from compd.codec import decode, encode
from compd.commissioning.plots import _runs, decode_words, trend_from_log, write_trend
from compd.log import read_log, write_log

PNG = b"\x89PNG\r\n\x1a\n"


def daemon_log(path, n=120, fault_rows=range(60, 70)):
    """A log as the daemon writes it (docs/formats.md): signals, pred_/corr_/applied_ per axis, word."""
    t = np.arange(n) * 10.0
    temp = 20.0 + 0.05 * np.arange(n)
    err_x1 = 2.0 * (temp - 20.0)
    err_x2 = -0.5 * (temp - 20.0)
    pred = np.column_stack([err_x1, err_x2])
    pred[list(fault_rows), 0] = np.nan  # the model had no prediction for x1: the guard faults it
    corr = -np.nan_to_num(pred)
    applied = np.round(corr)
    applied[np.abs(applied) <= 1.0] = 0.0
    word = np.array([encode(c1, c2) for c1, c2 in applied], dtype=float)
    cols = [
        "t_s",
        "T1",
        "speed_rpm",
        "err_x1_um",
        "err_x2_um",
        "pred_x1_um",
        "pred_x2_um",
        "corr_x1_um",
        "corr_x2_um",
        "applied_x1_um",
        "applied_x2_um",
        "word",
    ]
    data = np.column_stack([t, temp, np.full(n, 6000.0), err_x1, err_x2, pred, corr, applied, word])
    write_log(path, cols, data)
    return data


def test_decode_words_agrees_with_the_codec():
    words = np.array([0xC543, 0x0000, 0x4100, 0x00C1, 0xFFFF])
    um, en = decode_words(words, lsb_um=0.5)
    for k, w in enumerate(words):
        for slot, code in enumerate(decode(int(w))):
            assert en[k, slot] == code.enable
            want = code.direction * code.magnitude * 0.5 if code.enable else 0.0
            assert um[k, slot] == want
    assert um[0].tolist() == [2.5, -1.5]  # 0xC543: X1 +5 LSB, X2 -3 LSB


def test_runs_are_the_spans_of_true():
    assert _runs(np.array([0, 1, 1, 0, 1], bool)) == [(1, 3), (4, 5)]
    assert _runs(np.zeros(3, bool)) == []


def test_trend_from_daemon_log(tmp_path):
    data = daemon_log(tmp_path / "log.csv")
    trend = trend_from_log(read_log(tmp_path / "log.csv", allow_nan=True))
    assert trend.axes == ["x1", "x2"] and trend.word_axes == ["x1", "x2"]
    assert trend.lsb_um == 1.0 and any("no --config" in n for n in trend.notes)
    assert list(trend.signals) == ["T1"]  # speed_rpm is not a temperature; without a config only those
    assert trend.fault is not None
    assert np.flatnonzero(trend.fault[:, 0]).tolist() == list(range(60, 70))
    assert not trend.fault[:, 1].any()
    um, en = decode_words(trend.word, trend.lsb_um)
    np.testing.assert_array_equal(um, data[:, 9:11])  # the word carries what was applied here
    assert not en[0].any() and en[-1].all()  # dead-band at the start: disabled; enabled at the end


def test_trend_uses_the_configs_codec_and_inputs(tmp_path):
    daemon_log(tmp_path / "log.csv")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources:\n  - {kind: replay, name: log, path: log.csv}\n"
        "model: {kind: mlr, inputs: [T1, speed_rpm], outputs: [x1, x2],"
        " params: {coef_um_per_k: [[2.0, -0.5], [0.0, 0.0]], intercept_um: [0.0, 0.0]}}\n"
        "codec: {lsb_um: 0.5, axes: [x2, x1]}\n"
        "sink: {kind: fanuc_pmc}\n"
    )
    assert main(["check-config", str(cfg)]) == 0
    trend = trend_from_log(read_log(tmp_path / "log.csv", allow_nan=True), cfg)
    assert trend.lsb_um == 0.5 and trend.word_axes == ["x2", "x1"]
    assert list(trend.signals) == ["T1", "speed_rpm"]
    assert not trend.notes


def test_write_trend_draws_a_png(tmp_path):
    import matplotlib.image

    daemon_log(tmp_path / "log.csv")
    trend = trend_from_log(read_log(tmp_path / "log.csv", allow_nan=True))
    out = tmp_path / "t.png"
    write_trend(trend, out)
    img = matplotlib.image.imread(out)
    assert out.read_bytes()[:8] == PNG
    # inputs + (error, correction) per axis: five panels stacked, so taller than wide
    assert img.shape[0] > img.shape[1] > 800
    assert img[..., :3].std() > 0.1  # not blank


def test_cli_plot(tmp_path, capsys):
    daemon_log(tmp_path / "log.csv")
    out = tmp_path / "trend.png"
    assert main(["plot", str(tmp_path / "log.csv"), "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG
    assert "120 rows, axes x1, x2" in capsys.readouterr().out


@pytest.mark.parametrize(
    "content, words",
    [
        ("t_s,T1,err_x1_um\n0,20,0\n1,20,0\n", ["not a log that compd wrote", "applied_<axis>_um"]),
        ("t_s,T1,applied_x1_um,word\n0,20,0,0\n1,20,0,70000\n", ["word: ", "0..65535", "70000", "t_s = 1"]),
        ("t_s,T1,applied_x1_um,word\n0,20,0,0\n1,abc,0,0\n", ["T1"]),
        ("t_s,T1,applied_x1_um,word\n", ["no rows"]),
    ],
)
def test_cli_plot_bad_log_is_exit_2(tmp_path, capsys, content, words):
    log = tmp_path / "bad.csv"
    log.write_text(content)
    assert main(["plot", str(log), "--out", str(tmp_path / "t.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert str(log) in err
    for w in words:
        assert w in err
    assert not (tmp_path / "t.png").exists()


def test_cli_plot_bad_arguments_are_exit_2(tmp_path, capsys):
    daemon_log(tmp_path / "log.csv")
    assert main(["plot", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "t.png")]) == 2
    assert "nope.csv" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "log.csv"), "--out", str(tmp_path / "t.xyz")]) == 2
    assert "--out" in capsys.readouterr().err
    cfg = tmp_path / "c.yaml"
    cfg.write_text("loop: {period_s: 1.0}\nbogus: 1\n")
    assert main(["plot", str(tmp_path / "log.csv"), "--out", str(tmp_path / "t.png"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "c.yaml" in err and err.count("\n") == 1


def test_replay_trend_has_the_guards_fault_spans_and_the_words_bytes(tmp_path):
    """A replay through a config whose guard faults the axis on an out-of-range input: the
    trend's fault mask is the guard's state, and the commanded line is the word decoded."""
    from compd.commissioning.plots import trend_from_replay
    from compd.commissioning.replay import replay_config, write_plot
    from compd.cycle.limiter import FAULT, RECOVERING

    n = 200
    t = np.arange(n) * 10.0
    temp = 20.0 + 4.0 * (1 - np.exp(-t / 600.0))
    err = 3.0 * (temp - 20.0)
    temp[80:90] = 150.0  # out of the guard's range: the axis faults, then recovers
    write_log(tmp_path / "day.csv", ["t_s", "T1", "err_x1_um"], np.column_stack([t, temp, err]))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources:\n  - {kind: replay, name: log, path: day.csv}\n"
        "model: {kind: mlr, inputs: [T1], outputs: [x1], params: {coef_um_per_k: [[3.0]], intercept_um: [0.0]}}\n"
        "guard: {fault_policy: hold, recovery_s: 100, signals: {T1: {min: 0.0, max: 80.0}}}\n"
        "codec: {lsb_um: 0.5}\n"
        "sink: {kind: fanuc_pmc}\n"
    )
    result = replay_config(cfg, tmp_path / "day.csv")
    trend = trend_from_replay(result)
    state = result.extra["guard_state"][:, 0]
    assert trend.fault is not None
    np.testing.assert_array_equal(trend.fault[:, 0], (state == FAULT) | (state == RECOVERING))
    faulted = np.flatnonzero(trend.fault[:, 0])
    assert faulted[0] == 80 and 90 <= faulted[-1] < 110  # from the bad rows until recovery_s later
    um, _ = decode_words(trend.word, 0.5)
    assert trend.lsb_um == 0.5 and trend.word_axes == ["x1"]
    assert um[-1, 0] == pytest.approx(-err[-1], abs=1.0)  # the word commands −error
    assert list(trend.signals) == ["T1"]
    assert trend.scores["x1"]["reduction_pct"] > 50
    write_plot(result, tmp_path / "r.png")
    assert (tmp_path / "r.png").read_bytes()[:8] == PNG


def test_trend_from_log_marks_the_probes(tmp_path):
    data = daemon_log(tmp_path / "log.csv")
    probe = np.full(len(data), np.nan)
    probe[[30, 90]] = [4.0, 9.0]
    cols = read_log(tmp_path / "log.csv", allow_nan=True).columns + ["probe_x1_um", "probe_pos_x1_mm"]
    write_log(tmp_path / "p.csv", cols, np.column_stack([data, probe, probe * 0 + 100.0]))
    trend = trend_from_log(read_log(tmp_path / "p.csv", allow_nan=True))
    assert trend.probe_um is not None
    assert np.flatnonzero(np.isfinite(trend.probe_um[:, 0])).tolist() == [30, 90]
    assert trend.probe_um[90, 0] == 9.0 and not np.isfinite(trend.probe_um[:, 1]).any()
    assert "probe_pos_x1_mm" not in trend.signals and "probe_x1_um" not in trend.signals
    write_trend(trend, tmp_path / "p.png")
    assert (tmp_path / "p.png").read_bytes()[:8] == PNG


def test_replay_trend_shows_the_device_trailing_its_command(tmp_path):
    """A PMC allowed 1 µm every 30 s trails the word after each jump of the error: the trend's
    commanded line is the device's target (here the word's correction) and applied − commanded,
    the trailing panel's trace, shows by how much and how long; the PCI-1756 card (no rate of
    its own) applies its command at every row."""
    from compd.commissioning.plots import trailing_um, trend_from_replay
    from compd.commissioning.replay import replay_config, write_plot

    t = np.arange(0.0, 7200.0, 10.0)
    err = 2.0 * np.floor(t / 1200.0)  # +2 µm every 20 min: 2 LSB, 60 s for the slow PMC to follow
    temp = 20.0 + err / 3.0
    write_log(tmp_path / "day.csv", ["t_s", "T1", "err_x1_um"], np.column_stack([t, temp, err]))
    head = (
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources:\n  - {kind: replay, name: log, path: day.csv}\n"
        "model: {kind: mlr, inputs: [T1], outputs: [x1], params: {coef_um_per_k: [[3.0]], intercept_um: [0.0]}}\n"
        "guard: {max_slew_um_per_s: 10.0}\n"
    )
    (tmp_path / "slow.yaml").write_text(head + "sink: {kind: fanuc_pmc, max_step_um: 1, min_update_s: 30}\n")
    (tmp_path / "card.yaml").write_text(head + "sink: {kind: pci1756}\n")
    slow = trend_from_replay(replay_config(tmp_path / "slow.yaml", tmp_path / "day.csv"))
    um, _ = decode_words(slow.word, slow.lsb_um)
    np.testing.assert_array_equal(slow.commanded_um[:, 0], um[:, 0])  # the PMC's target is the word
    lag = trailing_um(slow, 0)
    # each 2 µm jump: the first 1 µm step in its own row (the PMC idle long enough), the second
    # 30 s after it, two rows later: 1 µm behind for two rows, after each of the 5 jumps
    assert lag.max() == 1.0 and lag.min() == 0.0
    assert (lag > 0).sum() == 2 * 5
    card = trend_from_replay(replay_config(tmp_path / "card.yaml", tmp_path / "day.csv"))
    assert not trailing_um(card, 0).any()
    for name, tr in (("slow", slow), ("card", card)):
        write_trend(tr, tmp_path / f"{name}.png")
        assert (tmp_path / f"{name}.png").read_bytes()[:8] == PNG
    write_plot(replay_config(tmp_path / "slow.yaml", tmp_path / "day.csv"), tmp_path / "r.png")
    assert (tmp_path / "r.png").read_bytes()[:8] == PNG


def test_a_siemens_daemon_log_commands_the_guards_correction(tmp_path):
    """`compd plot` of a daemon whose sink is the Siemens NC: the NC is sent the guard's
    correction (K0), so that is the commanded line (and the trailing is applied − correction)."""
    data = daemon_log(tmp_path / "log.csv")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources:\n  - {kind: replay, name: log, path: log.csv}\n"
        "model: {kind: mlr, inputs: [T1], outputs: [x1, x2],"
        " params: {coef_um_per_k: [[2.0, -0.5]], intercept_um: [0.0, 0.0]}}\n"
        "sink: {kind: siemens}\n"
    )
    trend = trend_from_log(read_log(tmp_path / "log.csv", allow_nan=True), cfg)
    np.testing.assert_allclose(trend.commanded_um, data[:, 7:9], rtol=0, atol=1e-9)
    assert "K0" in trend.commanded_label
    write_trend(trend, tmp_path / "t.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == PNG

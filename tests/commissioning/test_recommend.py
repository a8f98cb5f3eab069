"""`compd fit --kind all`'s recommendation: a sum of two stages only where it pays held out, its model
file (kind `contributions`) taken by everything that takes a model file, and cancellation said and
counted in what the report states."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.commissioning import fitting
from compd.commissioning import recommend as rec
from compd.log import Log, write_log
from tests.commissioning.test_fit_warnings import _lathe


@pytest.fixture(scope="module")
def lathe_sum(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Log, rec.SumOutcome]:
    """A lathe day and a sum of two stages on it (MLR on the head sensor, then MLR on the others)."""
    d = tmp_path_factory.mktemp("sum")
    lg = _lathe()
    write_log(d / "lathe.csv", lg.columns, lg.data)
    log = fitting.read_fit_log(d / "lathe.csv")
    (so,) = rec.propose_sums(log, [("mlr", "err_z_um", ["T1"], ["T1"], {})])
    return d, log, so


def _cand(label: str, held: float, **kw: object) -> rec.Candidate:
    return rec.Candidate(label, {"z": held}, {"z": [held * 0.8, held * 1.2]}, **kw)  # type: ignore[arg-type]


def test_a_sum_is_chosen_only_where_it_beats_the_best_single_model_by_the_margin(lathe_sum):
    _, _, so = lathe_sum
    single = _cand("mlr", 1.0)
    close = _cand("ar1+mlr", rec.SUM_MARGIN * 1.0 + 0.01, sum=so)
    better = _cand("ar1+mlr", rec.SUM_MARGIN * 1.0 - 0.01, sum=so)
    assert rec.choose([single, close], ["z"], {"z": 10.0}).candidate.label == "mlr"
    pick = rec.choose([single, better], ["z"], {"z": 10.0})
    assert pick.candidate.sum is so and pick.runner_up is single


def test_the_sum_is_scored_nested_no_stage_sees_the_fold(lathe_sum):
    """Each fold's two stages are fitted with its errors hidden: the pooled figure is above the
    in-sample RMS of the same two stages fitted on the whole log."""
    _, log, so = lathe_sum
    pred = rec.predict_fresh(so.first.model, log)[:, 0] + rec.predict_fresh(so.second.model, log)[:, 0]
    in_sample = float(np.sqrt(np.nanmean((log.col("err_z_um") - pred) ** 2)))
    assert len(so.scores) >= 2 and all(not isinstance(f, str) for f in so.scores)
    assert so.held_out_um > in_sample


def test_a_recommended_sum_is_one_model_file_for_replay_load_and_a_config(lathe_sum, tmp_path, capsys):
    d, log, so = lathe_sum
    pick = rec.choose([_cand(so.label, so.held_out_um, sum=so)], ["z"], {"z": 10.0})
    out = tmp_path / "model.yaml"
    fitting.write_recommended(pick, log, out)
    text = out.read_text()
    assert "&id" not in text and "*id" not in text  # no YAML aliases a reader has to follow
    data = yaml.safe_load(text)
    assert data["kind"] == "contributions" and [p["name"] for p in data["params"]["contributions"]] == list(
        fitting.STAGE_NAMES
    )
    assert data["fit"]["expected_unseen"]["z"]["rms_um"] == pytest.approx(so.held_out_um, rel=1e-3)
    assert data["fit"]["rows"] == len(log)

    model = fitting.load_model(out)  # what compd replay --model and compd score take
    want = rec.predict_fresh(so.first.model, log)[:, 0] + rec.predict_fresh(so.second.model, log)[:, 0]
    got = rec.predict_fresh(model, log)[:, 0]
    np.testing.assert_allclose(got[1:], want[1:], atol=1e-6)  # the sum ramps in from 0 at its first row

    assert main(["replay", "--model", str(out), "--log", str(d / "lathe.csv")]) == 0
    assert "axis z: RMS" in capsys.readouterr().out

    cfg = tmp_path / "c.yaml"  # a config's model: {kind: contributions, file: ...}, no guard written
    cfg.write_text(
        f"loop: {{clock: sim, period_s: 1.0}}\nsources:\n  - {{kind: replay, name: log, path: {d / 'lathe.csv'}}}\n"
        f"model: {{kind: contributions, file: {out}}}\nsink: {{kind: pci1756}}\n"
    )
    assert main(["check-config", str(cfg)]) == 0
    assert main(["replay", str(cfg), "--log", str(d / "lathe.csv")]) == 0
    assert "reduction" in capsys.readouterr().out


def test_a_model_file_of_contributions_refuses_limits_beside_it_in_one_line(lathe_sum, tmp_path, capsys):
    d, log, so = lathe_sum
    out = tmp_path / "model.yaml"
    fitting.write_recommended(rec.choose([_cand(so.label, 1.0, sum=so)], ["z"], {"z": 10.0}), log, out)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"loop: {{clock: sim, period_s: 1.0}}\nsources:\n  - {{kind: replay, name: log, path: {d / 'lathe.csv'}}}\n"
        f"model:\n  kind: contributions\n  file: {out}\n  max_abs_um: 10\nsink: {{kind: pci1756}}\n"
    )
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{cfg.name}:7:" in err and "model.contributions" in err


def test_a_default_limit_shorter_than_the_cycle_points_at_the_key_the_file_holds(tmp_path, capsys):
    """A 60 s loop (a log's row period) with no guard: the default stale limit (5 s) is named as a default
    with the key to add, at the line of loop.period_s — not at a line that holds no such key."""
    log = tmp_path / "l.csv"
    write_log(log, ["t_s", "T1", "err_z_um"], np.column_stack([np.arange(3.0) * 60, [20.0, 21, 22], [0.0, 1, 2]]))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"sources:\n  - {{kind: replay, name: log, path: {log}}}\nloop:\n  clock: sim\n  period_s: 60.0\n"
        "model: {kind: mlr, inputs: [T1], outputs: [z], params: {coef_um_per_k: [[1.0]]}}\n"
        "sink: {kind: pci1756}\n"
    )
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert f"{cfg.name}:5: loop.period_s: the default guard.stale_after_s" in err and "set guard.stale_after_s" in err


def test_stages_that_cancel_warn_and_widen_the_stated_range():
    t = np.linspace(0, 1, 200)
    p1, p2 = 26 * np.sin(3 * t), -26 * np.sin(3 * t) + 5 * t
    ratio = rec.cancel_ratio(p1, p2)
    assert ratio > rec.CANCEL_WARN
    plain = rec.Stated.of([0.8, 1.2], 1.0, 10.0)
    widened = rec.Stated.of([0.8, 1.2], 1.0, 10.0, ratio)
    assert widened.rms_um == plain.rms_um and widened.high_um == pytest.approx(plain.high_um * ratio / rec.CANCEL_WARN)
    assert math.isclose(rec.cancel_ratio(p1, p1), 1.0)

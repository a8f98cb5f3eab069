"""model.contributions: two heat sources on one axis, each its own model and limits, summed.

One's bad sensor leaves the other compensating; every channel shows each.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.commissioning.replay import replay_config, replay_log
from compd.config import load_config
from compd.cycle import pipeline
from compd.cycle.pipeline import build_model
from compd.cycle.statusblock import StatusBlock, compose, describe
from compd.log import read_log, write_log
from compd.plant.opcua import address_space
from compd.plant.telemetry import device_metrics
from compd.service.metrics import SnapshotCollector
from tests.commissioning.test_fit_residual import COLUMNS, _day

SLEW_UM_PER_S = 0.05  # the axis guard's (per log second: a row a minute)
RAMP_UM_PER_S = 0.002


@pytest.fixture(scope="module")
def plant(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A spindle model fitted on the spindle's own day, a column model fitted on what it leaves of a
    day of both sources, and an unseen day of both."""
    d = tmp_path_factory.mktemp("two_sources")
    _day(d / "spindle_day.csv", 1, column_heat=False)
    _day(d / "both.csv", 2, column_heat=True)
    _day(d / "unseen.csv", 3, column_heat=True)
    assert (
        main(
            [
                "fit",
                "--kind",
                "xi_spindle",
                "--log",
                str(d / "spindle_day.csv"),
                "--inputs",
                "T_spindle",
                "--out",
                str(d / "spindle.yaml"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "fit",
                "--kind",
                "mlr",
                "--log",
                str(d / "both.csv"),
                "--inputs",
                "T_col1",
                "T_col2",
                "--on-residual-of",
                str(d / "spindle.yaml"),
                "--out",
                str(d / "column.yaml"),
            ]
        )
        == 0
    )
    return d


def _config(d: Path, sink: str = "{kind: pci1756}", column: str = "", more: str = "", name: str = "two.yaml") -> Path:
    cfg = d / name
    cfg.write_text(f"""\
loop: {{clock: sim, period_s: 60.0}}
sources:
  - {{kind: replay, name: log, path: unseen.csv}}
model:
  contributions:
    - {{name: spindle, kind: xi_spindle, file: spindle.yaml, max_abs_um: 40}}
    - {{name: column, kind: mlr, file: column.yaml, fault_policy: ramp_to_zero{column}}}
guard: {{max_slew_um_per_s: {SLEW_UM_PER_S}, ramp_um_per_s: {RAMP_UM_PER_S}, stale_after_s: 200.0, recovery_s: 120}}
sink: {sink}
{more}""")
    return cfg


def test_the_sum_compensates_what_each_alone_cannot(plant: Path) -> None:
    result = replay_config(_config(plant), plant / "unseen.csv")
    z = result.report["axes"]["z"]
    parts = result.report["contributions"]["z"]
    assert z["rms_after_um"] < 0.1 * z["rms_before_um"]
    # each contribution alone leaves what the other one carries
    assert parts["spindle"]["alone_residual_rms_um"] > 3 * z["rms_after_um"]
    assert parts["column"]["alone_residual_rms_um"] > 3 * z["rms_after_um"]
    # the axis's prediction is the sum of the two shares, row by row
    shares = {name: share for name, _, share in result.extra["parts"]}
    np.testing.assert_allclose(shares["spindle"] + shares["column"], result.extra["pred_um"][:, 0], atol=1e-9)


def test_staged_replay_equals_the_loop_cycle_by_cycle(plant: Path) -> None:
    cfg = load_config(_config(plant))
    log = read_log(plant / "unseen.csv")
    runs = []
    for per_row in (False, True):
        sink_cls, sink_cfg, _ = cfg.sink
        sink = sink_cls(sink_cls.in_process_config(sink_cfg), base_dir=str(plant))
        runs.append(replay_log(log, build_model(cfg.model), sink, cfg.guard, cfg.codec, per_row=per_row))
    np.testing.assert_array_equal(runs[0].word, runs[1].word)
    np.testing.assert_allclose(runs[0].extra["pred_um"], runs[1].extra["pred_um"])
    assert runs[0].report["contributions"] == runs[1].report["contributions"]


def _unplugged(plant: Path, names: list[str], from_s: float) -> Path:
    """The unseen day with sensors' wires open from `from_s` on (NaN, as a PT100 module reads it)."""
    data = np.column_stack([read_log(plant / "unseen.csv").col(c) for c in COLUMNS])
    for name in names:
        data[data[:, 0] >= from_s, COLUMNS.index(name)] = np.nan
    out = plant / f"unplugged_{'_'.join(names)}.csv"
    write_log(out, COLUMNS, data)
    return out


def test_a_column_cable_pulled_ramps_the_column_out_alone(plant: Path) -> None:
    """Both column sensors lost (their cable): the column's model has nothing left to predict from."""
    cut_s = 3.5 * 3600
    log = _unplugged(plant, ["T_col1", "T_col2"], cut_s)
    cfg = _config(plant, more="log: {path: run.csv, period_s: 60}\n")
    text = cfg.read_text().replace("path: unseen.csv", f"path: {log.name}")
    cfg.write_text(text)
    result = replay_config(cfg, log)
    shares = {name: share for name, _, share in result.extra["parts"]}
    t = result.t_s
    after = t >= cut_s
    # the column's share ramps toward 0 at the guard's ramp rate, never faster
    col = shares["column"]
    assert abs(col[-1]) < abs(col[after][0])
    assert np.all(np.abs(np.diff(col[after])) <= RAMP_UM_PER_S * np.diff(t[after]) + 1e-9)
    # the spindle's share goes on following the spindle (it rises with the second run at 12000 rpm)
    sp = shares["spindle"]
    assert np.isfinite(sp).all() and sp[after].max() - sp[after].min() > 10.0
    # the axis never faulted, never stepped faster than its slew
    corr = result.extra["corr_um"][:, 0]
    assert np.all(np.abs(np.diff(corr)) <= SLEW_UM_PER_S * np.diff(t) + 1e-9)
    assert (result.extra["enable"][1:, 0]).all()
    faults = result.report["faults"]
    assert faults.get("fault:input bad") == 1  # the column's own fault event, not the axis's
    # with the spindle still compensated the residual stays far below the uncompensated error
    err = result.error_um[after, 0]
    left = err + result.applied_um[after, 0]
    assert np.sqrt(np.mean(left**2)) < 0.5 * np.sqrt(np.mean(err**2))


def test_one_column_sensor_lost_the_column_predicts_from_the_other(plant: Path) -> None:
    """One column sensor lost: the column's MLR predicts from the other (its degraded mode), no fault."""
    cut_s = 3.5 * 3600
    result = replay_config(_config(plant), _unplugged(plant, ["T_col1"], cut_s))
    assert "fault:input bad" not in result.report["faults"]
    assert result.report["faults"].get("degraded:inputs") == 1
    assert result.report["axes"]["z"]["rms_after_um"] < 0.2 * result.report["axes"]["z"]["rms_before_um"]


def test_disable_takes_the_axis_to_its_own_policy(plant: Path) -> None:
    cut_s = 3.5 * 3600
    log = _unplugged(plant, ["T_col1", "T_col2"], cut_s)
    cfg = _config(plant, column=", fault_policy: disable", name="disable.yaml")
    cfg.write_text(
        cfg.read_text().replace("fault_policy: ramp_to_zero, fault_policy: disable", "fault_policy: disable")
    )
    result = replay_config(cfg, log)
    after = result.t_s >= cut_s
    assert not np.isfinite(result.extra["pred_um"][after, 0]).any()
    faults = result.report["faults"]
    assert faults.get("fault:input bad") == 1 and faults.get("fault:prediction not finite") == 1  # its, then the axis's
    corr = result.extra["corr_um"][after, 0]
    assert np.all(corr == corr[0])  # the axis's own policy (guard.fault_policy: hold)


@pytest.mark.parametrize(
    "sink",
    [
        "{kind: pci1756}",
        "{kind: fanuc_pmc, mode: shift, r_command: 202, max_step_um: 5}",
        "{kind: siemens, axes: {z: 1}}",
    ],
)
def test_replay_through_each_sink(plant: Path, sink: str) -> None:
    cfg = _config(plant, sink=sink, name="sink.yaml")
    rc = main(["check-config", str(cfg)])
    assert rc == 0
    result = replay_config(cfg, plant / "unseen.csv")
    z = result.report["axes"]["z"]
    assert z["reduction_pct"] > 90.0, (sink, z)
    assert set(result.report["contributions"]["z"]) == {"spindle", "column"}


def test_every_channel_shows_each_contribution(plant: Path) -> None:
    cfg = load_config(_config(plant, more="log: {path: day.csv, period_s: 600}\nstatus: {path: status.json}\n"))
    assert main(["run", str(cfg.file)]) == 0
    log = read_log(plant / "day.csv", allow_nan=True)
    for col in ("pred_z_spindle_um", "pred_z_column_um"):
        assert np.isfinite(log.col(col)).all()
    np.testing.assert_allclose(
        log.col("pred_z_spindle_um") + log.col("pred_z_column_um"), log.col("pred_z_um"), atol=1e-3
    )  # as the log rounds them
    # the status record, composed as the service composes it, and what the plant's channels make of it
    p, _ = pipeline.from_config(cfg)
    loop = p.loop
    for row in range(30):
        loop.step(float(row) * 60.0)
    block = StatusBlock(loop)
    block.write()
    snap = compose(block.read(), describe(loop, False))
    parts = snap["axes"]["z"]["contributions"]
    assert set(parts) == {"spindle", "column"} and parts["spindle"]["state"] == "normal"
    assert parts["spindle"]["prediction_um"] + parts["column"]["prediction_um"] == pytest.approx(
        snap["axes"]["z"]["prediction_um"]
    )
    json.dumps(snap)
    names = {d.name for d, _ in device_metrics(snap)}
    assert {"Axis/z/Contribution/spindle/prediction_um", "Axis/z/Contribution/column/state"} <= names
    nodes = {v.node_id: v for v in address_space(snap, cfg.guard)}
    var = nodes["compd.Axes.z.Contributions.spindle.PredictionUm"]
    assert var.eu_range is not None and var.eu_range.high == 40.0  # its own clamp
    assert var.read(snap) is not None
    c = SnapshotCollector()
    c.update(snap, [], 0, 0.0)
    fams = {f.name: f for f in c.collect()}
    shares = {s.labels["contribution"]: s.value for s in fams["compd_contribution_meters"].samples}
    assert shares["spindle"] == pytest.approx(parts["spindle"]["prediction_um"] * 1e-6)


@pytest.mark.parametrize(
    ("section", "key", "message"),
    [
        (
            "[{name: a, kind: mlr, file: column.yaml}, {name: a, kind: xi_spindle, file: spindle.yaml}]",
            "model.contributions[1].name",
            "used twice",
        ),
        ("[{name: a, kind: mlr, file: column.yaml, max_abs_um: -1}]", "model.contributions[0].max_abs_um", ""),
        ("[{name: 'a b', kind: mlr, file: column.yaml}]", "model.contributions[0].name", ""),
        ("[{contributions: []}]", "model.contributions[0].contributions", "cannot itself"),
        ("[]", "model.contributions", ""),
    ],
)
def test_bad_contributions_are_one_line_errors(
    plant: Path, capsys: pytest.CaptureFixture[str], section: str, key: str, message: str
) -> None:
    cfg = plant / "bad.yaml"
    base = yaml.safe_load(_config(plant).read_text())
    text = _config(plant).read_text()
    start = text.index("model:")
    end = text.index("guard:")
    cfg.write_text(text[:start] + f"model:\n  contributions: {section}\n" + text[end:])
    assert base["model"]["contributions"]
    capsys.readouterr()
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.yaml" in err and key in err and message in err, err

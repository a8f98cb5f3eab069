"""Degraded prediction of the linear models when inputs go bad (issue: never throw the axis)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from compd.config import load_config
from compd.daemon.app import App
from compd.identify import FITS
from compd.log import Log
from compd.models.lvr import LVR
from compd.models.mlr import MLR


def synthetic_log(n: int = 1500, seed: int = 3) -> Log:
    """Nine sensors driven by two heat sources (so they are redundant) plus one lone sensor."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 60.0
    s1 = 8 * (1 - np.exp(-t / 4000)) * (1 + 0.3 * np.sin(t / 9000))
    s2 = 5 * (1 - np.exp(-t / 9000)) + 1.5 * np.sin(t / 5000)
    mix = rng.uniform(0.2, 1.0, (9, 2))
    temps = 20 + np.column_stack([s1, s2]) @ mix.T + rng.normal(0, 0.05, (n, 9))
    lone = 20 + 3 * np.sin(t / 3000) ** 2  # a sensor nobody else sees
    err = 1.8 * s1 + 1.1 * s2 + 2.0 * (lone - 20) + rng.normal(0, 0.1, n)
    cols = ["t_s"] + [f"T{i}" for i in range(1, 10)] + ["T_lone", "err_x_um"]
    return Log("synthetic.csv", cols, np.column_stack([t, temps, lone, err]))


def test_mlr_and_lvr_predict_from_the_remaining_sensors() -> None:
    log = synthetic_log()
    X = log.matrix(log.temperature_columns())
    y = log.col("err_x_um")
    for cls in (MLR, LVR):
        model = FITS.get(cls.kind)(log).model
        assert model.supports_degraded
        full = model.predict(X, log.t_s)[:, 0]
        out = np.zeros(1)
        good = np.ones(X.shape[1], dtype=bool)
        good[2] = False  # T3 lost: the other eight carry its information
        preds = []
        for row in X:
            bad_row = row.copy()
            bad_row[2] = np.nan
            model.evaluate_degraded(bad_row, good, 0.0, out)
            preds.append(out[0])
        preds = np.array(preds)
        rms_full = np.sqrt(np.mean((full - y) ** 2))
        rms_deg = np.sqrt(np.mean((preds - y) ** 2))
        assert np.isfinite(preds).all()
        assert rms_deg < rms_full + 1.0, (cls.kind, rms_full, rms_deg)
        assert model.degraded_sigma_um[0] < 2.0
        # the lone sensor carries unique information: the axis refuses to guess
        good[:] = True
        good[9] = False
        model.evaluate_degraded(X[100], good, 0.0, out)
        assert np.isnan(out[0]), cls.kind
        assert model.degraded_sigma_um[0] > 2.0


def test_loop_keeps_compensating_with_a_dead_sensor(tmp_path: Path) -> None:
    log = synthetic_log()
    model = FITS.get(LVR.kind)(log).model
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(model.to_dict()))
    data = log.data.copy()
    dead = (data[:, 0] > 30000) & (data[:, 0] < 60000)
    data_cols = log.columns
    lines = [",".join(data_cols)]
    for row, d in zip(data, dead, strict=True):
        cells = [f"{v:.6g}" for v in row]
        if d:
            cells[3] = ""  # T3 burnt out: empty cell → NO_DATA
        lines.append(",".join(cells))
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")  # empty cells: T3 dead
    (tmp_path / "c.yaml").write_text(
        """\
loop: {clock: sim, period_s: 60.0}
sources: [{kind: replay, name: log, path: log.csv}]
model: {kind: lvr, file: m.yaml}
guard: {max_slew_um_per_s: 0.5, stale_after_s: 120, fault_policy: hold}
sink: {kind: pci1756}
"""
    )
    app = App(load_config(tmp_path / "c.yaml"))
    seen = {"degraded": 0, "fault": 0}

    def watch(loop, now):  # noqa: ANN001
        seen["degraded"] += loop.degraded
        seen["fault"] += loop.guard.get_status()["x"]["state"] == "fault"

    app.loop.observers.append(watch)
    result = app.run()
    assert seen["degraded"] >= 400  # about 500 one-minute rows with T3 dead
    assert seen["fault"] == 0  # the axis never fell back to its fault policy
    assert result["faults"].get("degraded:inputs") == 1
    assert result["compensation"]["x"]["reduction_pct"] > 70

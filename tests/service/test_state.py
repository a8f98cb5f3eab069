"""Persisted model state: atomic writes, checked loading, restored across a restart."""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

from compd.config import load_config
from compd.daemon.app import App
from compd.service.state import StateWriter, load_saved, write_atomic

CONFIG = """\
loop: {clock: sim, period_s: 1.0}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {segments: [{duration_s: 7200, speed_rpm: 12000}]}
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {alpha_per_k: 13.6e-6, length_mm: 165.0}
sink: {kind: pci1756}
state: {path: state/model.json}
"""


def test_write_atomic_leaves_no_temp(tmp_path: Path) -> None:
    p = tmp_path / "s" / "state.json"
    write_atomic(p, {"a": 1})
    write_atomic(p, {"a": 2})
    assert json.loads(p.read_text()) == {"a": 2}
    assert [f.name for f in p.parent.iterdir()] == ["state.json"]


def test_load_state_checks(tmp_path: Path) -> None:
    p = tmp_path / "state.json"
    assert load_saved(p, "xi_spindle", ["T"], ["z"]) is None
    w = StateWriter(p, "xi_spindle", ["T"], ["z"])
    w.submit({"t0_c": 21.5})
    w.close()
    saved = load_saved(p, "xi_spindle", ["T"], ["z"])
    assert saved is not None and saved.state == {"t0_c": 21.5} and 0 <= saved.elapsed_s < 5
    assert load_saved(p, "ar1", ["T"], ["z"]) is None  # another model
    assert load_saved(p, "xi_spindle", ["T2"], ["z"]) is None
    raw = json.loads(p.read_text())
    raw["saved_unix_s"] = time.time() + 3600  # clock jumped back since
    p.write_text(json.dumps(raw))
    assert load_saved(p, "xi_spindle", ["T"], ["z"]) is None
    p.write_text("{not json")
    assert load_saved(p, "xi_spindle", ["T"], ["z"]) is None


def test_reference_survives_restart(tmp_path: Path) -> None:
    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text(CONFIG)
    first = App(load_config(cfg_path), duration_s=3600)
    first.run()
    t0 = first.model.t0_c
    saved = json.loads((tmp_path / "state" / "model.json").read_text())
    assert saved["state"]["t0_c"] == t0
    # restart on a warm spindle: the reference is the saved one, not the first new reading
    second = App(load_config(cfg_path), duration_s=10)
    second.sources[0].plant.advance_to(3600)
    second.run()
    assert second.model.t0_c == t0
    assert second.loop.pred_um[0] > 10.0  # still sees the growth since the cold start


def test_the_writer_never_saves_an_adapt_state_that_is_not_finite(tmp_path: Path, caplog) -> None:
    p = tmp_path / "state.json"
    w = StateWriter(p, "xi_spindle", ["T"], ["z"], params_sha256="abc")
    try:
        w.submit({"t0_c": 21.5})
        good = {"z": {"s": [1.0], "P": [[0.25]], "t_probe_s": 5.0, "accepted": 1, "rejected": 0, "probe_age_s": 0.0}}
        w.submit_adapt(good)
        with caplog.at_level(logging.ERROR, logger="compd"):
            w.submit_adapt({"z": {**good["z"], "P": [[math.nan]]}})  # a covariance gone NaN
            w.submit_adapt({"z": {**good["z"], "P": [[-4.0]]}})  # a negative variance
    finally:
        w.close()
    saved = json.loads(p.read_text())
    assert saved["adapt"]["axes"] == good  # the last good estimate is the one kept
    refused = [r for r in caplog.records if getattr(r, "event", None) == "adapt_state_refused"]
    assert len(refused) == 2 and "z: P[0]" in refused[0].reason and "semi-definite" in refused[1].reason


def test_a_time_stamp_no_float_holds_is_ignored_not_raised(tmp_path: Path) -> None:
    p = tmp_path / "state.json"
    p.write_text(
        '{"format": 1, "kind": "xi_spindle", "inputs": ["T"], "outputs": ["z"], "state": {},'
        ' "saved_unix_s": 1' + "0" * 400 + "}"
    )
    assert load_saved(p, "xi_spindle", ["T"], ["z"]) is None

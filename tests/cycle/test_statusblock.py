"""The status record: every field as the pipeline has it, a consistent copy across processes, docs from the schema."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from compd.config import load_config
from compd.cycle.statusblock import (
    AXIS,
    LI,
    LOOP,
    SIGNAL,
    StatusBlock,
    compose,
    describe,
    fields_markdown,
)
from compd.daemon.app import App
from compd.io.mailbox import shared_buffer
from tests.service_helpers import sim_config

ROOT = Path(__file__).resolve().parents[2]


def _ran(tmp_path: Path, cycles: int = 3000) -> App:
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    app.open()
    app.loop.run(max_cycles=cycles)
    return app


def test_the_record_holds_what_the_pipeline_has(tmp_path: Path) -> None:
    app = _ran(tmp_path)
    try:
        loop, g, fr = app.loop, app.guard, app.frame
        block = StatusBlock(loop)
        block.state = "running"
        block.rows_dropped = 7
        block.write()
        snap = compose(block.read(), describe(loop, observe=False))
        z = snap["axes"]["z"]
        assert z["prediction_um"] == float(loop.pred_um[0]) and z["correction_um"] == float(g.out_um[0])
        assert z["target_um"] == float(g.target_um[0]) and z["state"] == "normal" and z["inhibit"] is None
        assert z["guard_enable"] is True and z["enable"] is True  # the card is in process: its link is up
        word = loop.word
        assert z["byte"] == f"0x{(word >> 8) & 0xFF:02X}" and z["word_byte"] == "high"
        got = np.zeros(2)
        loop.sink.applied_um(got)
        assert z["applied_um"] == float(got[0]) and abs(z["applied_um"] - z["correction_um"]) < 1.0  # 1 µm steps
        for i, name in enumerate(fr.names):
            s = snap["signals"][name]
            assert s["value"] == float(fr.values[i]) and s["quality"] == "good"
            assert math.isclose(s["age_s"], loop.now_s - fr.stamp_s[i], abs_tol=1e-9)
        lp = snap["loop"]
        assert lp["cycles"] == loop.stats.cycles == 3000 and lp["misses"] == loop.stats.misses
        assert lp["lateness_us"] == loop.stats.lateness_us() and lp["cycle_compute_us"] == loop.stats.compute_us()
        assert lp["stages"] == loop.stats.stages()
        assert (
            snap["state"] == "running" and snap["word"] == f"0x{word:04X}" and snap["word_at_machine"] == snap["word"]
        )
        assert snap["publisher"]["rows_dropped"] == 7 and snap["publisher"]["status_write_max_us"] > 0
        assert snap["model"]["kind"] == app.model.kind and snap["sources"][0]["name"]
    finally:
        app.close()


def test_an_axis_held_at_the_guards_clamp_is_saturated_with_an_event(tmp_path: Path) -> None:
    """The model asks for more than max_abs_um: the record says saturated (the codec's byte is not
    at 63 LSB here) and the guard's `clamped` event is among the status's events."""
    app = _ran(tmp_path, cycles=10)
    try:
        loop, g = app.loop, app.guard
        g._max_abs[0] = 0.5  # a clamp the spindle's growth passes at once (the config's floor is higher)
        loop.run(max_cycles=200)
        block = StatusBlock(loop)
        block.write()
        snap = compose(block.read(), describe(loop, observe=False))
        z = snap["axes"]["z"]
        assert abs(z["prediction_um"]) > 0.5 and abs(z["target_um"]) == 0.5
        assert z["saturated"] is True and not loop.encoder.saturated[0]
        assert any(e["event"] == "clamped" and e["subject"] == "z" for e in snap["events"]), snap["events"]
    finally:
        app.close()


def test_a_reader_in_another_process_never_sees_a_half_written_record(tmp_path: Path) -> None:
    """The writer stamps one number into every field of a write; a forked reader checks that
    each copy it takes holds one number only (the seqlock). The writer goes on until the
    reader has seen 200 different writes (a condition, not a time), then writes the end."""
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    loop = app.loop
    block = StatusBlock(loop)
    counts = np.frombuffer(shared_buffer(16), dtype=np.int64)  # seen, torn (the reader's)
    end = -1.0
    pid = os.fork()
    if pid == 0:  # the reader
        last = math.nan
        while True:
            got = block.read()
            if got is None:
                continue
            v = got.axes[0, 0]
            if not (np.all(got.axes[[0, 1, 2]] == v) and np.all(got.signals[0] == v) and got.get(LI.loop_time_s) == v):
                counts[1] += 1
            if v != last:
                counts[0] += 1
                last = v
            if v == end:
                os._exit(0)

    def put(x: float) -> None:
        loop.pred_um[:] = x
        loop.guard.target_um[:] = x
        loop.guard.out_um[:] = x
        loop.frame.values[:] = x
        loop.now_s = x
        block.write()

    try:
        deadline = time.monotonic() + 120
        i = 0
        while counts[0] < 200 and time.monotonic() < deadline:
            put(float(i))
            i += 1
        put(end)
    finally:
        os.waitpid(pid, 0)
    assert counts[0] >= 200 and counts[1] == 0


def test_the_status_fields_page_is_generated_from_the_schema() -> None:
    page = (ROOT / "docs" / "status-fields.md").read_text(encoding="utf-8")
    assert page == fields_markdown(), (
        "docs/status-fields.md is stale: python -m compd.cycle.statusblock > docs/status-fields.md"
    )
    for f in (*AXIS, *SIGNAL, *LOOP):
        assert f"`{f.key}`" in page and f.meaning

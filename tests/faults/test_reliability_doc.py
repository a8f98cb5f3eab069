"""docs/reliability.md: the committed matrix has one row per matrix test and the generator's columns."""

from __future__ import annotations

from pathlib import Path

from compd.commissioning.faultdoc import (
    COLUMNS,
    read_block,
    render_matrix,
    replace_block,
    table_rows,
)
from tests.conftest import ROOT
from tests.faults.matrix import MATRIX

DOC = ROOT / "docs" / "reliability.md"


def test_every_matrix_row_has_a_test() -> None:
    """Each row id is recorded by a test in tests/faults (as a string literal in its source)."""
    sources = "".join(f.read_text() for f in Path(__file__).parent.glob("test_*.py") if f.name != Path(__file__).name)
    assert [row for row in MATRIX if f'"{row}"' not in sources] == []


def test_committed_doc_has_every_row_and_column() -> None:
    block = read_block(DOC.read_text(encoding="utf-8"), "faults")
    assert block is not None, "docs/reliability.md lacks the generated faults table"
    header, rows = table_rows(block)
    assert header == list(COLUMNS)
    ids = [r[0].strip("`") for r in rows]
    assert sorted(ids) == sorted(MATRIX), "regenerate: COMPD_FAULTS_OUT=build/faults pytest tests/faults"
    assert all(r[-1] == "yes" for r in rows), "a committed row shows a failed run"


def test_generator_round_trip() -> None:
    result = {
        "row": "x",
        "fault": "f | g",
        "transport": "t",
        "policy": "hold",
        "expected": "e",
        "max_step_um": 0.2,
        "allowed_step_um": 0.2,
        "max_step_ratio": 1.0,
        "time_to_safe_s": None,
        "samples_lost": 0,
        "event": "T bad: stale",
        "logged": True,
        "word_valid": True,
    }
    text = replace_block("# R\n\nprose\n", "faults", render_matrix([result]))
    text = replace_block(text, "faults", render_matrix([result, {**result, "row": "y"}]))
    header, rows = table_rows(read_block(text, "faults") or "")
    assert header == list(COLUMNS) and [r[0] for r in rows] == ["`x`", "`y`"]
    assert text.startswith("# R\n\nprose\n") and text.count("faults:begin") == 1
    assert rows[0][1] == "f \\| g" and rows[0][6] == "n/a"


def test_committed_doc_has_the_degraded_table() -> None:
    block = read_block(DOC.read_text(encoding="utf-8"), "degraded")
    assert block is not None, "run scripts/degraded_table.py --doc docs/reliability.md"
    header, rows = table_rows(block)
    assert header[0] == "sensor removed" and header[-1] == "axes served"
    singles = [r[0] for r in rows if not r[0].startswith(("(", "all of"))]
    assert len(singles) == 19 and len(set(singles)) == 19  # every gantry sensor removed once

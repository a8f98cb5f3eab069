"""The configuration reference is generated from the schema and committed up to date."""

from __future__ import annotations

import typing

from pydantic import BaseModel

from compd import config as c
from compd.commissioning.docgen import generate, unit_of


def test_committed_reference_is_current(root):
    committed = (root / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert committed == generate(), "docs/configuration.md is stale: run `make docs` (compd docs --out ...)"


def test_every_key_is_in_the_reference_with_its_default():
    text = generate()
    for key in c.LoopConfig.model_fields:
        assert f"| `{key}` |" in text
    assert "| `period_s` | number | s | `0.002` | ≥ 0.0005, ≤ 60 | cycle period (0.5 ms:" in text
    assert "| `max_slew_um_per_s` | number | µm/s | `5` | ≥ 0.0001, ≤ 1000 |" in text
    assert "at most 1048576 bytes" in text and "64 levels" in text  # the reader's limits
    for heading in ("### sources: kind sim", "### model: kind xi_spindle, params", "### sink: kind pci1756"):
        assert heading in text


def _models(model: type[BaseModel], seen: set) -> None:
    if model in seen:
        return
    seen.add(model)
    for f in model.model_fields.values():
        stack = [f.annotation]
        while stack:
            a = stack.pop()
            stack.extend(typing.get_args(a))
            if isinstance(a, type) and issubclass(a, BaseModel):
                _models(a, seen)


def test_every_core_key_has_a_description():
    seen: set = set()
    for m in (c.ConfigModel, c.ModelSection, c.SourceConfig, c.SinkConfig):
        _models(m, seen)
    missing = [f"{m.__name__}.{k}" for m in seen for k, f in m.model_fields.items() if not f.description]
    assert missing == []


def test_units_from_names():
    assert unit_of("period_s") == "s"
    assert unit_of("max_slew_um_per_s") == "µm/s"
    assert unit_of("alpha_per_k") == "1/K"
    assert unit_of("t0_c") == "°C"
    assert unit_of("length_mm") == "mm"
    assert unit_of("speed_rpm") == "rpm"
    assert unit_of("priority") == ""
    assert unit_of("_s") == ""

"""The status record's schema makes every channel: a field declared once reaches them all with its unit and meaning.

The channels are Prometheus, Sparkplug B and OPC UA; a key that is not declared cannot be read or written.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import pytest

from compd.cycle import statusblock
from compd.cycle.statusblock import AI, AXIS_SCOPE, FIELDS, LI, Field, _by_key, _scoped
from compd.service import metrics
from compd.service.metrics import EXAMPLE_SNAPSHOT, SnapshotCollector
from tests.service.test_promtool import _check

# one field more, declared as statusblock declares its own: everything below comes from it alone
NEW = _scoped(AXIS_SCOPE, Field("spindle_growth_um", "µm", "how far the spindle grew (a test's field)"))[0]


@pytest.fixture
def one_more_field(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """FIELDS with NEW, as each exporter sees it, and a snapshot whose axis z has it."""
    from compd.plant import opcua, telemetry

    for module in (statusblock, metrics, telemetry, opcua):
        monkeypatch.setattr(module, "FIELDS", (*FIELDS, NEW))
    snap = copy.deepcopy(EXAMPLE_SNAPSHOT)
    snap["axes"]["z"]["spindle_growth_um"] = 12.5
    snap["model"] = {"kind": "mlr", "fit": {}}
    return snap


def test_a_field_added_once_is_a_prometheus_family_in_its_base_unit(one_more_field: dict[str, Any]) -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    c = SnapshotCollector()
    c.update(one_more_field, [], 0, 0.0)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(c)
    text = generate_latest(registry).decode()
    assert "# HELP compd_spindle_growth_meters How far the spindle grew (a test's field)\n" in text
    assert "# TYPE compd_spindle_growth_meters gauge\n" in text
    sample = next(ln for ln in text.splitlines() if ln.startswith('compd_spindle_growth_meters{axis="z"} '))
    assert math.isclose(float(sample.split()[-1]), 12.5e-6)  # µm in meters
    checked = _check(text)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "compd_spindle_growth_meters" in metrics.metrics_markdown()  # the catalogue has it, with its unit
    assert "| m |" in next(ln for ln in metrics.metrics_markdown().splitlines() if "compd_spindle_growth" in ln)


def test_a_field_added_once_is_a_sparkplug_metric_with_its_unit(one_more_field: dict[str, Any]) -> None:
    from compd.plant.sparkplug import DataType, decode, encode
    from compd.plant.telemetry import device_metrics

    birth = decode(encode(device_metrics(one_more_field), timestamp_ms=1, seq=0, with_properties=True))
    m = next(m for m in birth.metrics if m.name == "Axis/z/spindle_growth_um")
    assert m.datatype == DataType.Double and m.value == 12.5 and m.properties == {"engUnit": "µm"}


def test_a_field_added_once_is_an_opcua_analog_node_with_its_unit_and_description(
    one_more_field: dict[str, Any],
) -> None:
    pytest.importorskip("asyncua")  # the `plant` extra
    from compd.core.config import GuardConfig
    from compd.plant.opcua import MICROMETRE, address_space, axis_range, data_values

    variables = address_space(one_more_field)
    var = next(v for v in variables if v.node_id == "compd.Axes.z.SpindleGrowthUm")
    assert var.data_type == "Double" and var.unit == MICROMETRE and var.analog
    assert var.description == "how far the spindle grew (a test's field)"
    assert var.eu_range == axis_range(GuardConfig(), "z")  # ± the guard's clamp of the axis
    values, problems = data_values(variables, one_more_field)
    value = values[variables.index(var)]
    assert (
        not [p for p in problems if "SpindleGrowth" in p] and value.Value.Value == 12.5 and value.StatusCode.is_good()
    )


def test_a_channel_leaves_a_field_out_only_with_a_reason() -> None:
    for f in FIELDS:
        for channel, why in f.omit:
            assert channel in statusblock.CHANNELS and len(why) > 20, (f.key, channel)
    with pytest.raises(ValueError, match="omit 'prometeus'"):
        Field("x_um", "µm", "x", omit=(("prometeus", "a misspelt channel"),))
    with pytest.raises(ValueError, match="the reason"):
        Field("x_um", "µm", "x", omit=(("prometheus", ""),))


def test_a_misspelt_key_is_refused() -> None:
    """The record's rows and the fields are named by their keys: a key no field has is an error where
    it is first used, never a wrong row; a field the schema cannot show is refused when declared."""
    assert AI.correction_um == 2 and LI.cycles == 3
    with pytest.raises(AttributeError):
        AI.corection_um  # noqa: B018
    with pytest.raises(AttributeError):
        statusblock.AX.corection_um  # noqa: B018
    with pytest.raises(ValueError, match="kind 'numbr'"):
        Field("x_um", "µm", "x", kind="numbr")
    with pytest.raises(ValueError, match="unit 'um'"):
        Field("x_um", "um", "x")
    with pytest.raises(ValueError):  # two fields of one key in a group: refused at import
        _by_key("Rows", (NEW, NEW), range(2))
    with pytest.raises(ValueError, match="no channel"):
        NEW.on("prometeus")


def test_the_cycle_writes_its_record_by_name_only() -> None:
    """StatusBlock.write names every row it writes (AI.…, LI.…): no row index typed as a number."""
    import inspect
    import re

    source = inspect.getsource(statusblock.StatusBlock.write)
    assert not re.findall(r"\b(?:v|ax|sg|pt)\[\d", source), "a row written by its number"
    assert json.dumps(source).count("LI.") >= 19


def test_the_exporters_type_no_key_of_the_record() -> None:
    """The exporters read the status record's fields through the schema: no field's key is typed in them."""
    from pathlib import Path

    keys = {f.key for f in FIELDS}
    root = Path(__file__).resolve().parents[2] / "compd"
    for path in ("service/metrics.py", "plant/telemetry.py", "plant/opcua.py"):
        source = (root / path).read_text(encoding="utf-8")
        typed = sorted({k for k in keys if f'"{k}"' in source or f"'{k}'" in source} - _ALSO_ELSEWHERE)
        assert not typed, f"{path} types {typed}"


# keys that are also keys of status.json outside the record (the loop's timing, a shadow's score, the model)
_ALSO_ELSEWHERE = {"state", "cycles", "misses", "skipped"}

"""The Grafana dashboard queries only metrics compd exports, and every one; docs/metrics.md is current."""

from __future__ import annotations

import json
import re
from typing import Any

from compd.cycle.statusblock import BASE_UNITS, FIELDS, PER_SIGNAL
from compd.service.metrics import (
    PROCESS_METRICS,
    SIGNAL_FAMILIES,
    families,
    metrics_markdown,
    sample_names,
    unit_of,
)

NAME = re.compile(r"\bcompd_[a-z0-9_]+")


def _dashboard(root) -> dict[str, Any]:
    return json.loads((root / "contrib" / "grafana" / "compd.json").read_text(encoding="utf-8"))


def _exprs(dash: dict[str, Any]) -> list[str]:
    out = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    for var in dash["templating"]["list"]:
        q = var.get("query")
        if isinstance(q, dict):
            out.append(q["query"])
    return out


def test_the_catalogue_has_every_family_the_collector_defines(root) -> None:
    source = (root / "compd" / "service" / "metrics.py").read_text(encoding="utf-8")
    defined = set(re.findall(r'MetricFamily\(\s*"(compd_[a-z0-9_]+)"', source))
    assert len(defined) >= 15
    # the families named from tables: one per signal unit, the processes' CPU and memory, a field of the status record
    defined |= {name for name, _, _ in SIGNAL_FAMILIES.values()} | {f"compd_process_{k}" for k, _, _ in PROCESS_METRICS}
    defined |= {f.metric_name() for f in FIELDS if f.on("prometheus") and f.unit != PER_SIGNAL}
    assert len(defined) >= 50
    assert {f.name for f in families()} == defined  # EXAMPLE_SNAPSHOT takes every branch


def test_every_query_names_an_exported_metric_and_every_family_has_a_panel(root) -> None:
    dash = _dashboard(root)
    exported = {f.name: set(sample_names(f)) for f in families()}
    scraped = set().union(*exported.values())
    queried = {n for e in _exprs(dash) for n in NAME.findall(e)}
    assert queried, "no query names a compd metric"
    assert queried <= scraped, f"not exported by compd/service/metrics.py: {sorted(queried - scraped)}"
    panel_exprs = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    for fam, names in exported.items():
        assert any(n in NAME.findall(e) for e in panel_exprs for n in names), f"no panel shows {fam}"


def test_the_data_source_is_templated(root) -> None:
    dash = _dashboard(root)
    variables = {v["name"]: v for v in dash["templating"]["list"]}
    assert variables["datasource"]["type"] == "datasource" and variables["datasource"]["query"] == "prometheus"
    for p in dash["panels"]:
        if p["type"] == "row":
            continue
        assert p["datasource"] == {"type": "prometheus", "uid": "${datasource}"}, p["title"]
        assert p["targets"] and all(t["datasource"]["uid"] == "${datasource}" for t in p["targets"])
        assert p["title"] and p["description"], p["id"]
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))
    assert "${datasource}" not in json.dumps(variables["datasource"])  # the variable is the source itself


def test_docs_list_every_metric_with_its_unit_and_are_current(root) -> None:
    text = (root / "docs" / "metrics.md").read_text(encoding="utf-8")
    assert text == metrics_markdown(), "docs/metrics.md is stale: run `compd docs --metrics --out docs/metrics.md`"
    for fam in families():
        row = next(ln for ln in text.splitlines() if f"`{sample_names(fam)[0]}`" in ln)
        assert f"| {unit_of(fam)} |" in row and fam.documentation in row
    assert "| m |" in text and "| s |" in text and "| °C |" in text  # base units


def test_quantiles_are_per_instance(root) -> None:
    """A histogram quantile over several daemons is each one's, never their merge."""
    exprs = [q for q in _exprs(_dashboard(root)) if "histogram_quantile" in q]
    assert exprs and all("by (le, instance)" in q for q in exprs), exprs


# a metric's unit (`unit_of`) → the Grafana unit ids that show it (fieldConfig.defaults.unit, or a
# series' override): the families are in base units, so meters, seconds, revolutions per second, …
GRAFANA_UNITS = {
    "m": {"lengthm"},
    "s": {"s"},
    "°C": {"celsius"},
    "K": {"kelvin"},
    "Hz": {"rothz"},
    "A": {"amp"},
    "V": {"volt"},
    "ratio": {"percentunit", "none"},
    "Pa": {"pressurepa"},
    "bytes": {"bytes", "decbytes"},
    "count": {"short", "none"},
    "0 or 1": {"none", "bool"},
    "16-bit word (0 … 65535)": {"hex0x"},
    "1": {"none"},
    "the signal's own (its name says none)": {"none", "short"},
}
# what a query does to its metric's unit: a rate or increase of a count is a count, a rate of CPU
# seconds a share of one CPU, bytes / 1e6 megabytes, now minus a start time a time
TRANSFORMS = (
    (re.compile(r"^rate\(\w+_seconds_total"), {"s": {"percentunit"}}),
    (re.compile(r"/ 1e6$"), {"bytes": {"decmbytes"}}),
    (re.compile(r"^time\(\) - "), {"s": {"s"}}),
)


def _series_unit(panel: dict[str, Any], ref: str) -> str | None:
    for o in panel["fieldConfig"].get("overrides", []):
        if o["matcher"] == {"id": "byFrameRefID", "options": ref}:
            return next(p["value"] for p in o["properties"] if p["id"] == "unit")
    return panel["fieldConfig"]["defaults"].get("unit")


def test_every_panel_and_series_shows_its_metrics_unit(root) -> None:
    """Each panel has a unit, and each query's series is shown in the unit of the metric it plots
    (metrics in base units: µm fields as meters, rpm signals as revolutions per second); a panel that
    plots metrics of several units gives each series its own (an override by query), so that no
    axis mixes a speed with an error without units."""
    units = {}
    for fam in families():
        for name in sample_names(fam):
            units[name] = unit_of(fam)
    # the status record's fields: the family's unit is the schema's, in its base unit
    base = {"meters": "m", "seconds": "s", "celsius": "°C", "kelvin": "K"}
    for f in FIELDS:
        if f.on("prometheus") and f.unit not in ("", PER_SIGNAL):
            assert units[f.metric_name()] == base[BASE_UNITS[f.unit][0]], f.key
    seen = 0
    for panel in _dashboard(root)["panels"]:
        if panel["type"] == "row":
            continue
        assert panel["fieldConfig"]["defaults"].get("unit"), f"panel {panel['title']!r} has no unit"
        for t in panel["targets"]:
            names = set(NAME.findall(t["expr"]))
            metric_units = {units[n] for n in names}
            assert len(metric_units) == 1, f"{panel['title']!r} {t['refId']}: one query, one unit: {metric_units}"
            (unit,) = metric_units
            allowed = GRAFANA_UNITS[unit]
            for pattern, changed in TRANSFORMS:
                if pattern.search(t["expr"]) and unit in changed:
                    allowed = changed[unit]
            shown = _series_unit(panel, t["refId"])
            assert shown in allowed, f"{panel['title']!r} {t['refId']} ({t['expr']}): {unit} shown as {shown!r}"
            seen += 1
    assert seen >= 40

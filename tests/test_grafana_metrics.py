"""The Grafana dashboard queries only metrics compd exports, and every one; docs/metrics.md is current."""

from __future__ import annotations

import json
import re
from typing import Any

from compd.cycle.statusblock import FIELDS, PER_SIGNAL
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
    assert len(defined) >= 25
    # the families named from tables: one per signal unit, the processes' CPU and memory, a field of the status record
    defined |= {name for name, _, _ in SIGNAL_FAMILIES.values()} | {f"compd_process_{k}" for k, _, _ in PROCESS_METRICS}
    defined |= {f.metric_name() for f in FIELDS if f.on("prometheus") and f.unit != PER_SIGNAL}
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

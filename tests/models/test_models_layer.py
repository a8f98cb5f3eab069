"""The evaluation side (compd/models/) is below identification: it imports nothing of compd.identify, not even
lazily or for type checking, and compd ships no benchmark code (benchmarks live in rig/)."""

from __future__ import annotations

import ast

from tests.conftest import ROOT


def _imported(path) -> set[str]:  # noqa: ANN001
    """Every module a file imports, at any depth (in functions, under TYPE_CHECKING)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out |= {node.module, *(f"{node.module}.{a.name}" for a in node.names)}
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module":
            out |= {a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)}
    return out


def test_models_import_nothing_of_identify() -> None:
    files = sorted((ROOT / "compd" / "models").glob("*.py"))
    assert files
    upward = {
        f.name: sorted(m for m in _imported(f) if m == "compd.identify" or m.startswith("compd.identify."))
        for f in files
    }
    assert {k: v for k, v in upward.items() if v} == {}


def test_fit_pls_is_defined_in_models_lvr() -> None:
    """The contract's `compd.models.lvr.fit_pls` is the PLS regression itself, not a call into identify."""
    from compd.identify import lvr as identify_lvr
    from compd.models import lvr

    assert lvr.fit_pls.__module__ == "compd.models.lvr" and lvr.fit_pls.__doc__
    assert identify_lvr.fit_pls is lvr.fit_pls


def test_compd_ships_no_benchmark_code() -> None:
    assert sorted(str(p.relative_to(ROOT)) for p in (ROOT / "compd").rglob("*bench*.py")) == []

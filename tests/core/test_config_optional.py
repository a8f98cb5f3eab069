"""A config that enables an optional feature whose module is not installed: one bad-input line, exit 2."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from compd.cli import main
from compd.config import OPTIONAL_MODULES
from tests.core.test_config import GOOD

METRICS = GOOD + "metrics: {enabled: true, bind: 127.0.0.1, port: 0}\n"


def test_check_config_names_the_key_of_a_missing_optional_module(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(METRICS)
    assert main(["check-config", str(p)]) == 0  # installed (the test extra): ok
    assert capsys.readouterr().out == "ok\n"
    monkeypatch.setitem(sys.modules, "prometheus_client", None)  # `import prometheus_client` now fails
    for command in (["check-config", str(p)], ["run", str(p), "--duration", "1"]):
        assert main(command) == 2
        out, err = capsys.readouterr()
        assert out == ""
        line = METRICS.splitlines().index("metrics: {enabled: true, bind: 127.0.0.1, port: 0}") + 1
        assert err == (
            f"compd: {p}:{line}: metrics.enabled: needs the Python module prometheus_client, which is"
            " not installed: pip install 'compd[metrics]'\n"
        )


def test_a_disabled_optional_feature_needs_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(GOOD + "metrics: {enabled: false}\n")
    for module, _ in OPTIONAL_MODULES.values():
        monkeypatch.setitem(sys.modules, module, None)
    assert main(["check-config", str(p)]) == 0
    assert capsys.readouterr().out == "ok\n"


def test_every_optional_module_has_its_extra_in_the_documented_setup() -> None:
    """`make demo` / `make install` install what the documented configs may enable."""
    import tomllib

    root = Path(__file__).resolve().parents[2]
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    makefile = (root / "Makefile").read_text()
    installed = makefile.split("pip install -q -e '.[", 1)[1].split("]'", 1)[0].split(",")
    for module, extra in OPTIONAL_MODULES.values():
        assert extra in extras, extra
        assert extra in installed, f"make demo does not install the {extra} extra ({module})"

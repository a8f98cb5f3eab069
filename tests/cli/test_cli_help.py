"""Every command's --help has a one-line description and an example; `compd --version`."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from compd import version
from compd.cli import build_parser, main
from compd.identify import KINDS, OPTIONS


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    p = build_parser()
    action = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_every_command_has_a_one_line_description_and_an_example() -> None:
    subs = _subparsers()
    assert {"run", "status", "fit", "check-config", "replay"} <= set(subs)
    for name, sp in subs.items():
        assert sp.description and "\n" not in sp.description.strip(), name
        assert sp.epilog and "example:" in sp.epilog and f"compd {name}" in sp.epilog, name
        assert "compd " in sp.format_help().split("example:")[-1], name


def test_version_prints_the_package_version(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"compd {version()}"
    out = subprocess.run([sys.executable, "-m", "compd", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["compd", version()]
    assert version().count(".") >= 2


def test_fit_help_lists_every_kinds_options_from_the_kinds_own_declaration(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = capsys.readouterr().out
    for kind in KINDS:
        assert f"  {kind}:" in text
        fields = OPTIONS.get(kind).model_fields
        for name, field in fields.items():
            assert f"    {name} (" in text, (kind, name)
            if field.description:
                assert field.description.split()[0] in text
    assert "  mlr: none" in text  # mlr declares no options
    assert "example:\n  compd fit --kind" in text

"""Kinds by name: compd's own table first, then the entry points of the registry's group."""

from __future__ import annotations

from importlib.metadata import EntryPoint

import pytest

from compd.core import registry
from compd.core.errors import BadInput
from compd.core.registry import Registry
from compd.sources.replay import ReplaySource

TABLE = {"replay": ("compd.sources.replay", "ReplaySource")}


def _with_plugins(monkeypatch: pytest.MonkeyPatch, *eps: EntryPoint) -> None:
    def entry_points(*, group: str, name: str | None = None) -> list[EntryPoint]:
        return [ep for ep in eps if ep.group == group and (name is None or ep.name == name)]

    monkeypatch.setattr(registry, "entry_points", entry_points)


def test_a_plugin_kind_is_found_through_the_group(monkeypatch):
    _with_plugins(monkeypatch, EntryPoint("extra", "compd.sources.replay:ReplaySource", "test.sources"))
    reg = Registry("source", TABLE, group="test.sources")
    assert reg.kinds() == ["extra", "replay"]
    assert reg.get("extra") is ReplaySource
    # without a group a registry sees no plug-in
    assert Registry("source", TABLE).kinds() == ["replay"]


def test_own_kinds_win_and_unknown_kinds_list_what_is_known(monkeypatch):
    _with_plugins(monkeypatch, EntryPoint("replay", "nowhere:Nothing", "test.sources"))
    reg = Registry("source", TABLE, group="test.sources")
    assert reg.get("replay") is ReplaySource
    with pytest.raises(BadInput, match=r"unknown source kind 'sim' \(known: replay\)"):
        reg.get("sim", path=("sources", 0, "kind"))


def test_a_plugin_that_cannot_be_imported_is_bad_input(monkeypatch):
    _with_plugins(monkeypatch, EntryPoint("sim", "no_such_package.sim:SimSource", "test.sources"))
    with pytest.raises(BadInput, match="kind 'sim' comes from no_such_package.sim:SimSource, which cannot be loaded"):
        Registry("source", TABLE, group="test.sources").get("sim")


def test_compd_bench_without_the_rig_is_exit_2(monkeypatch, capsys):
    from compd.cli import main

    _with_plugins(monkeypatch)
    assert main(["bench", "--cycles", "5"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("compd: `compd bench`") and "not installed" in err and len(err.splitlines()) == 1


def test_the_simulators_sim_source_is_installed_beside_compd():
    """The development install declares it (pyproject.toml); a stale install lacks it: reinstall."""
    from compd.sources import SOURCES

    assert SOURCES.get("sim").__module__ == "hil_sim.sim_source"

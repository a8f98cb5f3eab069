"""Lazy name → (module, class) tables for sources, models and sinks, keyed by YAML `kind`.

A table may also take kinds from other installed packages: a registry with an entry-point
`group` (e.g. `compd.sources`) looks a kind it does not define itself up among the
entry points of that group (`[project.entry-points."compd.sources"]` in the plug-in's
pyproject.toml, `kind = "package.module:Class"`). compd's own kinds always win.

Debian installs compd as two packages (packaging/deb/split.py): the daemon, `compd`, and
`compd-commissioning` (the fits, plots, reports, the simulator and the rig, scipy,
matplotlib, the OPC UA stack). With the daemon package alone, what the other one brings
is missing though compd's metadata names it; `part_missing` tells that case apart, so a
command, a kind or an extra that needs it says which package to install.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Sequence
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, TypeVar

from compd.core.errors import BadInput

COMMISSIONING_PACKAGE = "compd-commissioning"
# compd's own modules that only the commissioning commands import (the split's folders)
COMMISSIONING_MODULES = ("compd.identify", "compd.commissioning")
NOT_INSTALLED = f"part of the {COMMISSIONING_PACKAGE} package, which is not installed"


def commissioning_missing(e: BaseException) -> bool:
    """Whether `e` is the ImportError of a commissioning module (or one below it) that is not installed."""
    name = getattr(e, "name", None) or ""
    return isinstance(e, ModuleNotFoundError) and any(
        name == m or name.startswith(f"{m}.") for m in COMMISSIONING_MODULES
    )


def part_missing() -> bool:
    """Whether compd runs without its commissioning modules: the Debian daemon package alone (an
    install with pip always has them), where the rest of compd's distribution is missing too."""
    try:
        return importlib.util.find_spec(COMMISSIONING_MODULES[1]) is None
    except ImportError:
        return True


def install_hint(extra: str) -> str:
    """How to install what the extra `extra` of pyproject.toml brings, where compd runs now."""
    return f"install the {COMMISSIONING_PACKAGE} package" if part_missing() else f"pip install 'compd[{extra}]'"


def load_entry_point(ep: EntryPoint, what: str, *, path: Sequence[str | int] | None = None) -> Any:
    """The object an entry point names, or BadInput saying why it cannot be loaded (`what`: the
    kind or command it provides, for the message)."""
    try:
        return ep.load()
    except (ImportError, AttributeError) as e:
        if isinstance(e, ModuleNotFoundError) and part_missing():
            raise BadInput(f"{what} is {NOT_INSTALLED}", path=path) from None
        raise BadInput(f"{what} comes from {ep.value}, which cannot be loaded: {e}", path=path) from None


def entry_point(group: str, name: str) -> EntryPoint | None:
    """The installed entry point `name` of `group`, or None."""
    return next(iter(entry_points(group=group, name=name)), None)


T = TypeVar("T")


class Registry(Generic[T]):
    """A table of kinds; `get(kind)` imports the class on first use. `T` is what a kind names:
    a class (`Registry[type[Model]]`) or a function (the fits')."""

    def __init__(self, what: str, table: dict[str, tuple[str, str]], group: str | None = None) -> None:
        self.what = what
        self.table = table
        self.group = group

    def plugins(self) -> dict[str, EntryPoint]:
        """Kinds other installed packages add through the entry-point group (none without a group)."""
        if self.group is None:
            return {}
        return {ep.name: ep for ep in entry_points(group=self.group) if ep.name not in self.table}

    def kinds(self) -> list[str]:
        return sorted({*self.table, *self.plugins()})

    def get(self, kind: Any, *, path: Sequence[str | int] | None = None) -> T:
        if kind in self.table:
            module_name, class_name = self.table[kind]
            return getattr(importlib.import_module(module_name), class_name)
        plugin = self.plugins().get(kind) if isinstance(kind, str) else None
        if plugin is None:
            raise BadInput(
                f"unknown {self.what} kind {kind!r} (known: {', '.join(self.kinds())})",
                path=path,
            )
        return load_entry_point(plugin, f"{self.what} kind {kind!r}", path=path)

"""Lazy name → (module, class) tables for sources, models and sinks, keyed by YAML `kind`.

A table may also take kinds from other installed packages: a registry with an entry-point
`group` (e.g. `compd.sources`) looks a kind it does not define itself up among the
entry points of that group (`[project.entry-points."compd.sources"]` in the plug-in's
pyproject.toml, `kind = "package.module:Class"`). compd's own kinds always win.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, TypeVar

from compd.core.errors import BadInput


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
        try:
            return plugin.load()
        except (ImportError, AttributeError) as e:
            raise BadInput(
                f"{self.what} kind {kind!r} comes from {plugin.value}, which cannot be loaded: {e}", path=path
            ) from None

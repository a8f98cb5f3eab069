"""Lazy name → (module, class) tables for sources, models and sinks, keyed by YAML `kind`."""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from typing import Any

from compd.errors import BadInput


class Registry:
    """A table of kinds; `get(kind)` imports the class on first use."""

    def __init__(self, what: str, table: dict[str, tuple[str, str]]) -> None:
        self.what = what
        self.table = table

    def kinds(self) -> list[str]:
        return sorted(self.table)

    def get(self, kind: Any, *, path: Sequence[str | int] | None = None) -> type:
        if kind not in self.table:
            raise BadInput(
                f"unknown {self.what} kind {kind!r} (known: {', '.join(self.kinds())})",
                path=path,
            )
        module_name, class_name = self.table[kind]
        module = importlib.import_module(module_name)
        return getattr(module, class_name)

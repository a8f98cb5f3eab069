"""A log CSV as a source: each cycle publishes the last row at or before the loop time."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from compd.core.config import SourceConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.log import Log, read_log
from compd.sources.base import Source


class ReplayConfig(SourceConfig):
    """Replay of a log written by compd or a simulator (the log CSV of docs/formats.md)."""

    path: str = Field(description="log CSV, relative to the config")
    columns: list[str] | None = Field(None, description="columns to publish; none = all but t_s")


class ReplaySource(Source):
    """Publishes the logged signals on the loop clock; empty cells read as NO_DATA."""

    Config = ReplayConfig

    def __init__(self, cfg: ReplayConfig, base_dir: str = ".", log: Log | None = None) -> None:
        from pathlib import Path

        super().__init__(cfg, base_dir)
        if log is None:
            path = Path(cfg.path)
            if not path.is_absolute():
                path = Path(base_dir) / path
            if path.exists() and not path.is_file():  # /dev/zero, a FIFO: reading would never end
                raise BadInput("cannot read log: not a regular file", file=str(path))
            log = read_log(path, allow_nan=True)
        self.log = log
        self._names = cfg.columns or log.columns[1:]
        self._data = log.matrix(self._names)
        self._t = log.t_s
        self._row = -1
        self._good = ~np.isnan(self._data)

    @property
    def start_s(self) -> float:
        return float(self._t[0]) if len(self._t) else 0.0

    @property
    def end_s(self) -> float:
        return float(self._t[-1]) if len(self._t) else 0.0

    def signal_names(self) -> list[str]:
        return list(self._names)

    def read(self, frame: Frame, now_s: float) -> None:
        t = self._t
        row = self._row
        while row + 1 < len(t) and t[row + 1] <= now_s:
            row += 1
        self._row = row
        if row < 0:
            frame.quality[self._idx] = Quality.NO_DATA
            return
        frame.values[self._idx] = self._data[row]
        frame.quality[self._idx] = np.where(self._good[row], Quality.GOOD, Quality.NO_DATA)
        frame.stamp_s[self._idx] = t[row]

    def get_status(self) -> dict[str, Any]:
        return {**super().get_status(), "row": self._row, "rows": len(self._t)}

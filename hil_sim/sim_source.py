"""compd's `sim` source kind: a hil_sim plant stepped in process on the loop's clock.

compd does not know this kind: it finds it through the `compd.sources` entry point
that this package declares (pyproject.toml), so `kind: sim` works wherever hil_sim is
installed beside compd (`make demo`, the tests) and is an unknown kind where it is not.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from compd.core.config import SourceConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.sources.base import Source
from hil_sim.plants import PLANTS
from hil_sim.scenario import Scenario


class SimConfig(SourceConfig):
    """An in-process plant: `plant` names the machine, `scenario` its duty cycle."""

    plant: str = Field(description="hil_sim plant name, e.g. spindle")
    scenario: str | dict[str, Any] = Field(
        description="scenario YAML file (relative to the config) or an inline scenario"
    )
    params: dict[str, Any] = Field(default_factory=dict, description="plant parameters")
    sample_period_s: float = Field(0.0, ge=0, le=3600, description="sensor update period; 0 = every cycle")


class SimSource(Source):
    """Publishes the plant's sensor readings and its true errors (`err_<axis>_um`)."""

    Config = SimConfig

    def __init__(self, cfg: SimConfig, base_dir: str = ".") -> None:
        super().__init__(cfg, base_dir)
        try:
            if isinstance(cfg.scenario, str):
                path = Path(cfg.scenario)
                if not path.is_absolute():
                    path = Path(base_dir) / path
                scenario = Scenario.load(path)
            else:
                scenario = Scenario.from_dict(dict(cfg.scenario))
            self.plant = PLANTS.get(cfg.plant)(scenario, cfg.params)
        except (OSError, ValueError, TypeError) as e:
            raise BadInput(f"sim source {cfg.name!r}: {e}") from None
        self.scenario = scenario
        self._next_sample_s = -np.inf
        self._last = np.full(len(self.plant.signal_names), np.nan)
        self._stamp = -np.inf

    @property
    def start_s(self) -> float:
        """The scenario starts at loop time 0."""
        return 0.0

    @property
    def end_s(self) -> float:
        """The scenario's end (s): a run on the sim clock without a duration stops there."""
        return self.scenario.duration_s

    def signal_names(self) -> list[str]:
        return list(self.plant.signal_names)

    def read(self, frame: Frame, now_s: float) -> None:
        if now_s >= self._next_sample_s:
            self.plant.advance_to(now_s)
            self._last[:] = self.plant.sample()
            self._stamp = now_s
            self._next_sample_s = now_s + self.cfg.sample_period_s
        frame.values[self._idx] = self._last
        frame.quality[self._idx] = Quality.GOOD
        frame.stamp_s[self._idx] = self._stamp

    def get_status(self) -> dict[str, Any]:
        return {**super().get_status(), "plant": self.cfg.plant, "plant_t_s": self.plant.t_s}

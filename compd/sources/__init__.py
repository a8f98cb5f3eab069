"""Signal sources, one module per transport, found by YAML `kind`.

Other packages add source kinds through the `compd.sources` entry-point group (the
simulator's `sim` source is one).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from compd.core.registry import Registry

if TYPE_CHECKING:
    from compd.sources.base import Source

SOURCES: Registry[type[Source]] = Registry(
    "source",
    {
        "replay": ("compd.sources.replay", "ReplaySource"),
        "modbus": ("compd.sources.modbus", "ModbusSource"),
        "dcon": ("compd.sources.dcon", "DconSource"),
        "can": ("compd.sources.can", "CanSource"),
        "probe": ("compd.sources.probe", "ProbeSource"),
        "hal": ("compd.sources.hal", "HalSource"),
    },
    group="compd.sources",
)

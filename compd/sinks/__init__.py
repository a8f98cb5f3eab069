"""Correction sinks, one module per output, found by YAML `kind`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from compd.core.registry import Registry

if TYPE_CHECKING:
    from compd.sinks.base import Sink

SINKS: Registry[type[Sink]] = Registry(
    "sink",
    {
        "pci1756": ("compd.sinks.pci1756", "Pci1756Sink"),
        "fanuc_pmc": ("compd.sinks.fanuc_pmc", "FanucPmcSink"),
        "siemens": ("compd.sinks.siemens", "SiemensSink"),
        "linuxcnc": ("compd.sinks.linuxcnc", "LinuxcncSink"),
    },
)

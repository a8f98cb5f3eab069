"""Correction sinks, one module per output, found by YAML `kind`."""

from compd.core.registry import Registry

SINKS = Registry(
    "sink",
    {
        "pci1756": ("compd.sinks.pci1756", "Pci1756Sink"),
        "fanuc_pmc": ("compd.sinks.fanuc_pmc", "FanucPmcSink"),
        "siemens": ("compd.sinks.siemens", "SiemensSink"),
        "linuxcnc": ("compd.sinks.linuxcnc", "LinuxcncSink"),
    },
)

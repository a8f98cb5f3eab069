"""Correction sinks, one module per output, found by YAML `kind`."""

from compd.registry import Registry

SINKS = Registry(
    "sink",
    {
        "pci1756": ("compd.sinks.pci1756", "Pci1756Sink"),
    },
)

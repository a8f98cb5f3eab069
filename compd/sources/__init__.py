"""Signal sources, one module per transport, found by YAML `kind`."""

from compd.registry import Registry

SOURCES = Registry(
    "source",
    {
        "sim": ("compd.sources.sim", "SimSource"),
        "replay": ("compd.sources.replay", "ReplaySource"),
        "modbus": ("compd.sources.modbus", "ModbusSource"),
        "dcon": ("compd.sources.dcon", "DconSource"),
        "can": ("compd.sources.can", "CanSource"),
    },
)

"""The simulated machines, found by name."""

from __future__ import annotations

from typing import TYPE_CHECKING

from compd.core.registry import Registry

if TYPE_CHECKING:
    from hil_sim.plants.base import Plant

PLANTS: Registry[type[Plant]] = Registry(
    "plant",
    {
        "spindle": ("hil_sim.plants.spindle", "SpindlePlant"),
        "feed_axis": ("hil_sim.plants.feed_axis", "FeedAxisPlant"),
        "lathe": ("hil_sim.plants.lathe", "LathePlant"),
        "gantry": ("hil_sim.plants.gantry", "GantryPlant"),
        "vmc": ("hil_sim.plants.vmc", "VmcPlant"),
    },
)

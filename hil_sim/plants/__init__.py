"""The simulated machines, found by name."""

from compd.core.registry import Registry

PLANTS = Registry(
    "plant",
    {
        "spindle": ("hil_sim.plants.spindle", "SpindlePlant"),
        "feed_axis": ("hil_sim.plants.feed_axis", "FeedAxisPlant"),
        "lathe": ("hil_sim.plants.lathe", "LathePlant"),
        "gantry": ("hil_sim.plants.gantry", "GantryPlant"),
        "vmc": ("hil_sim.plants.vmc", "VmcPlant"),
    },
)

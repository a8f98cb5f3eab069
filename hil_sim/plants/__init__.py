"""The simulated machines, found by name."""

from compd.registry import Registry

PLANTS = Registry(
    "plant",
    {
        "spindle": ("hil_sim.plants.spindle", "SpindlePlant"),
    },
)

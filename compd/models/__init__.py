"""Thermal-error models, one module each, found by YAML `kind`."""

from compd.core.registry import Registry

MODELS = Registry(
    "model",
    {
        "xi_spindle": ("compd.models.xi_spindle", "XiSpindle"),
        "feed_axis": ("compd.models.feed_axis", "FeedAxis"),
        "lvr": ("compd.models.lvr", "LVR"),
        "ar1": ("compd.models.ar1", "AR1"),
        "mlr": ("compd.models.mlr", "MLR"),
    },
)

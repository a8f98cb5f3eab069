"""Thermal-error models, one module each, found by YAML `kind`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from compd.core.registry import Registry

if TYPE_CHECKING:
    from compd.models.base import Model

MODELS: Registry[type[Model]] = Registry(
    "model",
    {
        "xi_spindle": ("compd.models.xi_spindle", "XiSpindle"),
        "feed_axis": ("compd.models.feed_axis", "FeedAxis"),
        "lvr": ("compd.models.lvr", "LVR"),
        "ar1": ("compd.models.ar1", "AR1"),
        "mlr": ("compd.models.mlr", "MLR"),
    },
)

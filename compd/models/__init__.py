"""Thermal-error models, one module each, found by YAML `kind` (SPEC §3)."""

from compd.registry import Registry

MODELS = Registry(
    "model",
    {
        "xi_spindle": ("compd.models.xi_spindle", "XiSpindle"),
    },
)

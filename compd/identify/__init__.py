"""Identification apart from evaluation: the fits that estimate each model kind's coefficients from a log.

One module per kind (`fit(log, inputs, targets, **options) -> FitResult` and its `Options`),
found by YAML `kind` like the run-time models; compd.identify.data is the shared data
preparation. Only `compd fit` (compd.fitting) and the offline tools import this package:
the daemon evaluates models without it (and without scipy or tqdm).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from compd.registry import Registry

if TYPE_CHECKING:
    from compd.identify.data import FitResult
    from compd.log import Log

KINDS = ("feed_axis", "lvr", "xi_spindle", "ar1", "mlr")

FITS = Registry("model", {kind: (f"compd.identify.{kind}", "fit") for kind in KINDS})
OPTIONS = Registry("model", {kind: (f"compd.identify.{kind}", "Options") for kind in KINDS})


def identify(
    kind: str, log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any
) -> FitResult:
    """Fit a model of `kind` to a log (`compd fit`).

    `inputs`/`targets` None means the kind's defaults (every temperature column, every
    `err_*_um` column); `options` are validated against the kind's `Options`. The report
    holds what is specific to the kind (Q², Ljung–Box, convergence); compd.fitting adds the
    common figures (rows, RMSE, max error, fit time).
    """
    return FITS.get(kind, path="--kind")(log, inputs, targets, **options)


def option_names(kind: str) -> set[str]:
    """The fit options `kind` takes."""
    return set(OPTIONS.get(kind).model_fields)


def options_help(width: int = 100) -> str:
    """The fit options of every kind, as `compd fit --help` lists them: one line per option
    with its type, default and description, from the kinds' own `Options` (imports scipy)."""
    import textwrap

    lines = ["fit options per kind (--option KEY=VALUE, the value read as YAML):"]
    for kind in KINDS:
        fields = OPTIONS.get(kind).model_fields
        lines.append(f"  {kind}:" + ("" if fields else " none"))
        for name, f in fields.items():
            ann = f.annotation
            kind_of = ann.__name__ if isinstance(ann, type) else str(ann).replace("typing.", "")
            default = "required" if f.is_required() else f"default {f.default!r}"
            text = f"{name} ({kind_of}, {default})" + (f": {f.description}" if f.description else "")
            lines += textwrap.wrap(text, width, initial_indent="    ", subsequent_indent="        ")
    return "\n".join(lines)

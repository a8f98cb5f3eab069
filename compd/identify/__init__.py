"""Identification apart from evaluation: the fits that estimate each model kind's coefficients from a log.

One module per kind (`fit(log, inputs, targets, **options) -> FitResult` and its `Options`),
found by YAML `kind` like the run-time models; compd.identify.data is the shared data
preparation. Only `compd fit` (compd.commissioning.fitting) and the offline tools import this package:
the daemon evaluates models without it (and without scipy or tqdm).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from compd.core.registry import Registry
from compd.identify.lag import HELD_INPUTS, fit_with_lag

if TYPE_CHECKING:
    from collections.abc import Callable

    from compd.core.config import Strict
    from compd.identify.data import FitResult
    from compd.log import Log

KINDS = ("feed_axis", "lvr", "xi_spindle", "ar1", "mlr")

FITS: Registry[Callable[..., FitResult]] = Registry(
    "model", {kind: (f"compd.identify.{kind}", "fit") for kind in KINDS}
)
OPTIONS: Registry[type[Strict]] = Registry("model", {kind: (f"compd.identify.{kind}", "Options") for kind in KINDS})
CHOICES: Registry[Callable[[FitResult], dict[str, Any]]] = Registry(
    "model", {kind: (f"compd.identify.{kind}", "choices") for kind in KINDS}
)
# the fit option every kind takes: the inputs' sensor lag (compd.identify.lag); the MLR baseline
# stays the papers' model unless asked
COMMON_OPTIONS = {
    "lag": "the inputs' sensor lag: auto (chosen held out; off where it does not help), off,"
    " seconds for every temperature input, or {input: seconds}; default auto (mlr: off)"
}


def default_lag(kind: str) -> str:
    """The `lag` option when none is given: auto, but off for mlr (the papers' baseline)."""
    return "off" if kind == "mlr" else "auto"


def identify(
    kind: str, log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any
) -> FitResult:
    """Fit a model of `kind` to a log (`compd fit`), with its inputs' sensor lag (compd.identify.lag).

    `inputs`/`targets` None means the kind's defaults (every temperature column, every
    `err_*_um` column); `options` are validated against the kind's `Options` (plus `lag`). The
    report holds what is specific to the kind (Q², Ljung–Box, convergence, the lag); compd.commissioning.fitting
    adds the common figures (rows, RMSE, max error, fit time).
    """
    fit = FITS.get(kind, path="--kind")
    options = dict(options)
    lag = options.pop("lag", default_lag(kind))
    if "lag" in OPTIONS.get(kind).model_fields:  # the kind chooses its lead itself (with its sensors, in one pass)
        return fit(log, inputs, targets, lag=lag, **options)

    def run(lg: Log, opts: dict[str, Any]) -> FitResult:
        opts = dict(opts)
        held = opts.pop(HELD_INPUTS, None)
        return fit(lg, inputs if held is None else held, targets, **opts)

    return fit_with_lag(log, targets, run, options, lag, CHOICES.get(kind))


def option_names(kind: str) -> set[str]:
    """The fit options `kind` takes."""
    return set(OPTIONS.get(kind).model_fields) | set(COMMON_OPTIONS)


def options_help(width: int = 100) -> str:
    """The fit options of every kind, as `compd fit --help` lists them: one line per option
    with its type, default and description, from the kinds' own `Options` (imports scipy)."""
    import textwrap

    lines = ["fit options per kind (--option KEY=VALUE, the value read as YAML):"]
    for name, text in COMMON_OPTIONS.items():
        lines += textwrap.wrap(f"every kind: {name}: {text}", width, initial_indent="  ", subsequent_indent="      ")
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

"""A probe measurement and the checks every path that takes one applies (the cycle's adapter, the probe socket)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from compd.core.config import MAX_CORRECTION_UM, SIGNAL_ABS_MAX

# what a probe may carry: thermal errors are tens to hundreds of µm
MAX_PROBE_ERROR_UM = MAX_CORRECTION_UM  # 10 mm: larger than any clamp compd accepts, so no thermal error
MAX_PROBE_SIGMA_UM = 1000.0  # a probe scattered by more than 1 mm says nothing of such errors
MIN_PROBE_SIGMA_UM = 0.001  # 1 nm, the probe block's resolution: no probe of a machine tool is finer
MAX_PROBE_POSITION_MM = SIGNAL_ABS_MAX  # as any signal's limit: a position beyond ±10⁶ mm is a typo


def finite_number(value: Any) -> bool:
    """True for an int or a float that is finite as a float (not a bool, not an int beyond a float's range)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int of hundreds of digits
        return False


def brief(value: Any, limit: int = 40) -> str:
    """`value` as an error message shows it: its repr, cut to `limit` characters with how long it was."""
    try:
        text = repr(value)
    except ValueError:  # an int of more digits than Python converts
        return "an int of thousands of digits"
    return text if len(text) <= limit else f"{text[: limit - 3]}… ({len(text)} characters)"


def probe_problem(error_um: Any, sigma_um: Any = None, position_mm: Any = None) -> tuple[str, str] | None:
    """Why a probe's numbers cannot be taken: (the key, why), or None. `sigma_um` and `position_mm`
    None: not given (the config's σ; no position)."""
    if not finite_number(error_um):
        return "error_um", f"must be a finite number, got {brief(error_um)}"
    if abs(error_um) > MAX_PROBE_ERROR_UM:
        return "error_um", f"{error_um:g} um is beyond ±{MAX_PROBE_ERROR_UM:g} um: no thermal error is that large"
    if sigma_um is not None:
        if not finite_number(sigma_um):
            return "sigma_um", f"must be a finite number, got {brief(sigma_um)}"
        if not MIN_PROBE_SIGMA_UM <= sigma_um <= MAX_PROBE_SIGMA_UM:
            return "sigma_um", (
                f"must be within [{MIN_PROBE_SIGMA_UM:g}, {MAX_PROBE_SIGMA_UM:g}] um, got {sigma_um:g}"
                " (beyond 1 mm a probe says nothing; below 1 nm no probe measures)"
            )
    if position_mm is not None:
        if not finite_number(position_mm):
            return "position_mm", f"must be a finite number, got {brief(position_mm)}"
        if abs(position_mm) > MAX_PROBE_POSITION_MM:
            return "position_mm", f"{position_mm:g} mm is beyond ±{MAX_PROBE_POSITION_MM:g} mm"
    return None


@dataclass(frozen=True)
class Probe:
    """One probe measurement: the thermal error the machine measured on an axis at time t_s."""

    t_s: float
    axis: str
    error_um: float
    sigma_um: float | None = None  # None: the config's sigma_um
    position_mm: float | None = None
    source: str = "probe"
    # True: `error_um` is the deviation measured with the correction in place (what a probe
    # on a compensated machine sees); the adapter adds back the correction applied then
    # (on a slope axis with a position: when the axis last stood there, `Adapter.at_position`)
    residual: bool = False

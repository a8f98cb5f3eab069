"""The error function on numpy arrays without scipy: the C library's erf (Python's math.erf) value by value.

The daemon's models evaluate with this (a feed axis has a few dozen segments per cycle);
fits, which evaluate large arrays many times, pass scipy.special.erf instead
(compd.identify). The two agree to a few ulp (tests/models/test_erf.py).
"""

from __future__ import annotations

import math

import numpy as np

_erf_each = np.frompyfunc(math.erf, 1, 1)


def erf(x: np.ndarray | float) -> np.ndarray:
    """erf(x) elementwise, float64, any shape."""
    return np.asarray(_erf_each(np.asarray(x, dtype=float)), dtype=float)


def erf_inplace(buf: np.ndarray) -> None:
    """erf of a short 1-D float array, in place (the per-cycle path; through a list, twice as
    fast as item by item on numpy scalars)."""
    buf[:] = list(map(math.erf, buf.tolist()))

"""The error function erf on numpy arrays without scipy, with the numbers of scipy.special.erf.

`erf` (arrays: batch prediction and fits): for |x| ≤ 1, erf(x) = x T(x²)/U(x²); above,
erf(x) = 1 − e^(−x²) P(x)/Q(x) (|x| < 8) or 1 − e^(−x²) R(x)/S(x), with the polynomials of
the Cephes library (S. L. Moshier) that scipy evaluates. Evaluated in the same order, the
numbers are scipy's (tests/models/test_erf.py). `erf_inplace` (the 30-odd values of one
loop cycle): the C library's erf value by value, within 3 ulp of scipy's and many times
faster there than a numpy pass.
"""

from __future__ import annotations

import math

import numpy as np

# Numerators lead with the highest power; the denominators' leading coefficient 1 is implied.
_T = (9.60497373987051638749e0, 9.00260197203842689217e1, 2.23200534594684319226e3,
      7.00332514112805075473e3, 5.55923013010394962768e4)
_U = (3.35617141647503099647e1, 5.21357949780152679795e2, 4.59432382970980127987e3,
      2.26290000613890934246e4, 4.92673942608635921086e4)
_P = (2.46196981473530512524e-10, 5.64189564831068821977e-1, 7.46321056442269912687e0,
      4.86371970985681366614e1, 1.96520832956077098242e2, 5.26445194995477358631e2,
      9.34528527171957607540e2, 1.02755188689515710272e3, 5.57535335369399327526e2)
_Q = (1.32281951154744992508e1, 8.67072140885989742329e1, 3.54937778887819891062e2,
      9.75708501743205489753e2, 1.82390916687909736289e3, 2.24633760818710981792e3,
      1.65666309194161350182e3, 5.57535340817727675546e2)
_R = (5.64189583547755073984e-1, 1.27536670759978104416e0, 5.01905042251180477414e0,
      6.16021097993053585195e0, 7.40974269950448939160e0, 2.97886665372100240670e0)
_S = (2.26052863220117276590e0, 9.39603524938001434673e0, 1.20489539808096656605e1,
      1.70814450747565897222e1, 9.60896809063285067085e0, 3.36907645100081516050e0)
_BIG = 30.0  # erf(x) rounds to ±1 from |x| ≈ 6 on; clipping keeps ∞ out of the polynomials


def _rows(*polys: tuple[tuple[float, ...], bool]) -> np.ndarray:
    """One row of 9 coefficients per polynomial, highest power first, padded with leading zeros
    (Horner's rule through a zero prefix starts exactly at the first coefficient); a monic
    polynomial gets its implied leading 1."""
    rows = []
    for coef, monic in polys:
        full = ((1.0,) if monic else ()) + coef
        rows.append((0.0,) * (9 - len(full)) + full)
    return np.array(rows)


# T/U in x², P/Q in |x| below 8, R/S in |x| from 8 on: evaluated together, one Horner pass.
_COEF = _rows((_T, False), (_U, True), (_P, False), (_Q, True), (_R, False), (_S, True))


def erf(x: np.ndarray | float, out: np.ndarray | None = None) -> np.ndarray:
    """erf(x) elementwise (float64); written into `out` when given (may be `x` itself)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:  # one number: the 1-element array's
        one = erf(x.reshape(1))[0]
        if out is None:
            return one
        out[...] = one
        return out
    a = np.abs(x)
    np.minimum(a, _BIG, out=a)  # NaN stays NaN
    far = bool(a.max(initial=0.0) >= 8.0)  # the R/S rows only when needed (rare)
    n = 6 if far else 4
    v = np.empty((n,) + a.shape)
    np.multiply(a, a, out=v[0])
    v[1] = v[0]
    v[2:] = a
    cols = _COLS[n][a.ndim] if a.ndim < 3 else _columns(n, a.ndim)
    acc = np.empty_like(v)
    acc[...] = cols[0]
    for c in cols[1:]:
        np.multiply(acc, v, out=acc)
        np.add(acc, c, out=acc)
    small = a * acc[0]
    small /= acc[1]
    if far:
        near = a < 8.0
        num, den = np.where(near, acc[2], acc[4]), np.where(near, acc[3], acc[5])
    else:
        num, den = acc[2], acc[3]
    big = np.exp(-v[0])
    big *= num
    big /= den
    np.subtract(1.0, big, out=big)
    res = np.where(a <= 1.0, small, big)
    if out is None:
        return np.copysign(res, x)
    np.copysign(res, x, out=out)
    return out


def _columns(n: int, ndim: int) -> list[np.ndarray]:
    """The coefficient columns of the first `n` polynomials, shaped to broadcast on (n, *shape)."""
    coef = _COEF[:n].reshape((n,) + (1,) * ndim + (9,))
    return [np.ascontiguousarray(coef[..., k]) for k in range(9)]


_COLS = {n: [_columns(n, d) for d in range(3)] for n in (4, 6)}


def erf_inplace(buf: np.ndarray) -> None:
    """erf of a short 1-D float array, in place, value by value with math.erf (the C library's)."""
    buf[:] = list(map(math.erf, buf.tolist()))

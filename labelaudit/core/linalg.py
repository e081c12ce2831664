"""Small dense linear algebra (matrices up to 8×8) for the per-box model, at a fraction of the call cost.

``np.linalg`` wraps each LAPACK call in type checks, an ``errstate`` context and result
wrapping, which on a 6×6 matrix cost several times the arithmetic (a box runs about ten such
calls). These functions call the same NumPy gufuncs (``numpy.linalg._umath_linalg``, float64
signature) directly, so their results are bit-identical to ``np.linalg`` (a test checks); they
fall back to ``np.linalg`` when that module is not there. Errors stay errors: a matrix that is not
positive definite or is singular raises, as in ``np.linalg``. No I/O.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

try:  # the gufuncs behind np.linalg (present in NumPy 1.x and 2.x)
    from numpy.linalg import _umath_linalg as _UL
except ImportError:  # pragma: no cover - another NumPy layout: use the public API
    _UL = None

FloatArray = NDArray[np.float64]

__all__ = ["cholesky", "eigh", "inv", "solve"]


def inv(a: FloatArray) -> FloatArray:
    """``np.linalg.inv`` of a float64 square matrix; raises ``np.linalg.LinAlgError`` when singular."""
    if _UL is None:
        return np.linalg.inv(a)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = _UL.inv(a, signature="d->d")
    if out[0, 0] != out[0, 0]:  # LAPACK failed: the gufunc filled the result with NaN
        return np.linalg.inv(a)  # raises the LinAlgError np.linalg gives (or returns what it returns)
    return out


def cholesky(a: FloatArray) -> FloatArray:
    """Lower Cholesky factor, as ``np.linalg.cholesky``; raises ``np.linalg.LinAlgError`` when ``a``
    is not positive definite."""
    if _UL is None:
        return np.linalg.cholesky(a)
    with np.errstate(invalid="ignore"):
        out = _UL.cholesky_lo(a, signature="d->d")
    if out[0, 0] != out[0, 0]:  # not positive definite: NaN-filled
        return np.linalg.cholesky(a)  # raises LinAlgError
    return out


def solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.linalg.solve(a, b)`` for a float64 square ``a`` and a float64 matrix ``b`` (2-D);
    raises ``np.linalg.LinAlgError`` when ``a`` is singular."""
    if _UL is None:
        return np.linalg.solve(a, b)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = _UL.solve(a, b, signature="dd->d")
    if out.size and out[0, 0] != out[0, 0]:
        return np.linalg.solve(a, b)
    return out


def eigh(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``np.linalg.eigh(a)`` (lower triangle) of a float64 symmetric matrix: eigenvalues ascending,
    eigenvectors as columns; raises ``np.linalg.LinAlgError`` when LAPACK does not converge."""
    if _UL is None:
        return np.linalg.eigh(a)
    with np.errstate(invalid="ignore"):
        w, v = _UL.eigh_lo(a, signature="d->dd")
    if w.size and w[0] != w[0]:
        return np.linalg.eigh(a)
    return w, v

"""Small dense linear algebra (matrices up to 8×8) for the per-box model, at a fraction of the call cost.

``np.linalg`` wraps each LAPACK call in type checks, an ``errstate`` context and result
wrapping, which on a 6×6 matrix cost several times the arithmetic (a box runs about ten such
calls). These functions call the same NumPy gufuncs (``numpy.linalg._umath_linalg``, float64
signature) directly, so their results are bit-identical to ``np.linalg`` (a test checks); they
fall back to ``np.linalg`` when that module is not there. Errors stay errors: a matrix that is not
positive definite or is singular raises, as in ``np.linalg``. It also holds :func:`pairwise_sum`,
NumPy's summation order, and :func:`nan_max` / :func:`nan_min` (``np.maximum`` / ``np.minimum`` of two
floats), for compiled kernels that must reproduce NumPy's results (numba's cache does not see a
change here from the kernels of other modules that inline them: clear their ``__pycache__/*.nb*``
after editing these). No I/O.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from labelaudit.kernels import kernel

try:  # the gufuncs behind np.linalg (present in NumPy 1.x and 2.x)
    from numpy.linalg import _umath_linalg as _UL
except ImportError:  # pragma: no cover - another NumPy layout: use the public API
    _UL = None

FloatArray = NDArray[np.float64]

__all__ = ["cholesky", "eigh", "inv", "nan_max", "nan_min", "pairwise_sum", "solve"]


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


@kernel
def _pairwise_block(a, lo, n):  # pragma: no cover - compiled
    """NumPy's sum of a block of n ≤ 128 elements: 8 accumulators (sequential below 8 elements)."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@kernel
def pairwise_sum(a):  # pragma: no cover - compiled
    """``a.sum()`` of a 1-D float64 array with NumPy's order of operations (0 + pairwise sum:
    halves rounded to multiples of 8 until a block has ≤ 128 elements), so compiled code can
    reproduce a NumPy total bit for bit (tests/test_linalg.py checks it). The split tree is
    walked with an explicit stack: numba's cache does not load recursive functions reliably."""
    if a.size <= 128:
        return 0.0 + _pairwise_block(a, 0, a.size)
    seg_lo = np.empty(64, dtype=np.int64)
    seg_n = np.empty(64, dtype=np.int64)
    left = np.empty(64)
    right_pending = np.zeros(64, dtype=np.bool_)  # the left half of this segment is summed
    top = 0
    seg_lo[0], seg_n[0] = 0, a.size
    while True:
        n = seg_n[top]
        if n > 128:  # split: visit the left half first
            n2 = n // 2
            n2 -= n2 % 8
            right_pending[top] = False
            top += 1
            seg_lo[top], seg_n[top] = seg_lo[top - 1], n2
            continue
        v = _pairwise_block(a, seg_lo[top], n)
        while top > 0:  # hand the sum up the tree
            top -= 1
            if not right_pending[top]:
                left[top] = v
                right_pending[top] = True
                n2 = seg_n[top] // 2
                n2 -= n2 % 8
                top += 1
                seg_lo[top], seg_n[top] = seg_lo[top - 1] + n2, seg_n[top - 1] - n2
                break
            v = left[top] + v
        else:
            return 0.0 + v


@kernel
def nan_max(a: float, b: float) -> float:  # pragma: no cover - compiled
    """np.maximum of two floats (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@kernel
def nan_min(a: float, b: float) -> float:  # pragma: no cover - compiled
    """np.minimum of two floats (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a <= b else b
